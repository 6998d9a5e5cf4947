"""The web client's zstd decoder ships in the package (src/psao/web/vendor/fzstd.mjs and its LICENSE, served
as /vendor/fzstd.js): the copy equals the ESM build of the fzstd that web/package-lock.json pins, as
`npm ci` in web/ installs it (`make test` runs it first; without web/node_modules the comparison skips).
So do the three.js files of the three.js example (vendor/three/, from web/three/'s lockfile)."""
from __future__ import annotations

import json

import pytest

from conftest import REPO
from psao.server.net.webpage import THREE_FILES, WEB_DIR, answer

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


THREE_NPM = REPO / "web" / "three"
THREE = THREE_NPM / "node_modules" / "three"


def test_shipped_three_is_the_locked_npm_package():
    """src/psao/web/vendor/three/ holds, byte for byte, the files of the three.js that web/three's lockfile
    pins (the build and the addons the example imports); each is served under /vendor/three/."""
    pinned = json.loads((THREE_NPM / "package.json").read_text())["dependencies"]["three"]
    locked = json.loads((THREE_NPM / "package-lock.json").read_text())["packages"]["node_modules/three"]
    assert locked["version"] == pinned and locked["license"] == "MIT"
    shipped = WEB_DIR.joinpath("vendor", "three")
    for f in THREE_FILES:
        served = answer(f"/vendor/three/{f}")
        assert served.status == 200 and served.content_type.startswith("text/javascript"), f
        assert served.body == shipped.joinpath(*f.split("/")).read_bytes()
    if not THREE.is_dir():
        pytest.skip("web/three/node_modules is missing (npm ci in web/three/)")
    assert json.loads((THREE / "package.json").read_text())["version"] == locked["version"]
    for f in THREE_FILES:
        npm = THREE / ("build/" + f if not f.startswith("addons/") else "examples/jsm/" + f.removeprefix("addons/"))
        assert shipped.joinpath(*f.split("/")).read_bytes() == npm.read_bytes(), \
            f"src/psao/web/vendor/three/{f} differs from the locked three's {npm.relative_to(THREE)}: copy it from web/three/node_modules"
    assert shipped.joinpath("LICENSE").read_bytes() == (THREE / "LICENSE").read_bytes()
