"""The web client's zstd decoder ships in the package (src/psao/web/vendor/fzstd.mjs and its LICENSE, served
as /vendor/fzstd.js): the copy equals the ESM build of the fzstd that web/package-lock.json pins, as
`npm ci` in web/ installs it (`make test` runs it first; without web/node_modules the comparison skips)."""
from __future__ import annotations

import json

import pytest

from conftest import REPO
from psao.server.net.webpage import WEB_DIR, answer

NPM = REPO / "web"
FZSTD = NPM / "node_modules" / "fzstd"


def test_the_page_serves_the_shipped_decoder():
    served = answer("/vendor/fzstd.js")
    assert served.status == 200 and served.content_type.startswith("text/javascript")
    assert served.body == WEB_DIR.joinpath("vendor", "fzstd.mjs").read_bytes()
    assert "MIT License" in WEB_DIR.joinpath("vendor", "LICENSE").read_text()


def test_shipped_decoder_is_the_locked_npm_package():
    pinned = json.loads((NPM / "package.json").read_text())["dependencies"]["fzstd"]
    locked = json.loads((NPM / "package-lock.json").read_text())["packages"]["node_modules/fzstd"]
    assert locked["version"] == pinned and locked["license"] == "MIT"
    if not FZSTD.is_dir():
        pytest.skip("web/node_modules is missing (make test runs npm ci in web/)")
    assert json.loads((FZSTD / "package.json").read_text())["version"] == locked["version"]
    assert WEB_DIR.joinpath("vendor", "fzstd.mjs").read_bytes() == (FZSTD / "esm" / "index.mjs").read_bytes(), \
        "src/psao/web/vendor/fzstd.mjs differs from the locked fzstd's esm/index.mjs: copy it from web/node_modules"
    assert WEB_DIR.joinpath("vendor", "LICENSE").read_bytes() == (FZSTD / "LICENSE").read_bytes()
