"""Mirror checks from digest logs: the jsonl lines `psao serve --digest-log` (ServeSettings.digest_log) and
`psao client --digest-log` write, {"conn", "seq", "tick", "digest"}, one per message that left the client's
mirror equal to the server's state."""
from __future__ import annotations

import json
from pathlib import Path


def read_jsonl(path: Path) -> list[dict]:
    """The records of a jsonl file (none when it is missing); a line still being written is skipped."""
    path = Path(path)
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    return out


def compare_digests(server_log: Path, client_logs) -> tuple[int, int, set]:
    """(pairs compared, pairs different, connections compared): every (connection, message) that both the
    server and a client logged must have the same state digest."""
    ours = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(server_log)}
    compared = differ = 0
    conns = set()
    for f in client_logs:
        for d in read_jsonl(f):
            if (d["conn"], d["seq"]) in ours:
                compared += 1
                differ += ours[d["conn"], d["seq"]] != d["digest"]
                conns.add(d["conn"])
    return compared, differ, conns
