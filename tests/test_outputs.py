"""Output files: checked before the work, written to a temporary file and renamed, nothing partial left."""
from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from psao.server.errors import ConfigError
from psao.server.grid import Grid
from psao.server.outputs import check_output_path, write_atomically
from support.cli import one_line_error, psao

NOBODY_UID = 65534  # the unprivileged user root's checks switch to
BAKE = ["bake", "builtin:cornell", "--density", "8", "--rays", "1", "--probes", "0"]


def test_bake_writes_the_named_file_atomically(tmp_path):
    out = tmp_path / "new" / "grid.npz"
    proc = psao(*BAKE, "--out", str(out), "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.splitlines()[-1])["out"] == str(out.resolve())
    grid, _, _ = Grid.load(out)
    assert len(grid.cells) > 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["grid.npz"]  # no temporary left


@pytest.mark.parametrize("make, text", [
    (lambda d: "/dev/full", "is not a regular file"),
    (lambda d: str(d), "is a folder"),
    (lambda d: str(d / "grid"), "the name must end in .npz"),
    (lambda d: (d / "file.txt").write_text("x") and str(d / "file.txt" / "grid.npz"), "is not a folder"),
])
def test_bad_output_paths_fail_before_the_bake(tmp_path, make, text):
    proc = psao(*BAKE, "--out", make(tmp_path))
    one_line_error(proc, text)
    assert "points kept" not in proc.stderr  # refused before baking


def test_a_failing_write_leaves_nothing(tmp_path):
    target = check_output_path(tmp_path / "grid.npz", ".npz")

    def write(f):
        f.write(b"half a grid")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(ConfigError, match="cannot write .*No space left on device"):
        write_atomically(target, write)
    assert list(tmp_path.iterdir()) == []


@contextlib.contextmanager
def folder_permissions_apply():
    """Inside the block, folder permissions bind this process: root (who writes anywhere) runs it with the
    effective user switched to nobody's; any other user runs it as itself."""
    if os.geteuid() != 0:
        yield
        return
    os.seteuid(NOBODY_UID)
    try:
        yield
    finally:
        os.seteuid(0)


def test_read_only_folder_refused():
    # a folder of its own under the temporary folder: pytest's tmp_path lies in folders only root may enter
    base = Path(tempfile.mkdtemp())
    folder = base / "ro"
    try:
        base.chmod(0o755)
        folder.mkdir()
        folder.chmod(0o555)
        with folder_permissions_apply(), pytest.raises(ConfigError, match="cannot write in .*Permission denied"):
            check_output_path(folder / "grid.npz", ".npz")
        assert list(folder.iterdir()) == []
    finally:
        if folder.exists():
            folder.chmod(0o755)
        shutil.rmtree(base)


def test_atomic_write_replaces_an_existing_file(tmp_path):
    target = tmp_path / "a.npz"
    target.write_bytes(b"old")
    write_atomically(target, lambda f: np.savez(f, x=np.arange(3)))
    assert np.load(target)["x"].tolist() == [0, 1, 2]
