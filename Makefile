# Two entry points: `make demo` and `make test`. Both create or refresh .venv first.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

NPM_STAMP := web/node_modules/.package-lock.json

.PHONY: demo test venv bench clean browser

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "make: $(PYTHON) not found (Python 3.11+ is required)"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

# The pinned fzstd and three from npm, which tests/test_web_vendor.py checks the copies in src/psao/web/vendor/
# against (the package ships those copies; installing psao needs no npm).
$(NPM_STAMP): web/package-lock.json web/three/package-lock.json
	cd web && npm ci --no-audit --no-fund --loglevel=error
	cd web/three && npm ci --no-audit --no-fund --loglevel=error
	touch $(NPM_STAMP)

# The browser the web client's tests drive (playwright's Python API with Debian's chromium, no download).
browser:
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && apt-get update -q && apt-get install -y -q chromium; } \
		|| echo "make: chromium is not installed and this is not root: the browser tests will skip"

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/psao demo

test: $(STAMP) $(NPM_STAMP) browser
	$(BIN)/python -m pytest -q -ra

bench: $(STAMP)
	$(BIN)/python -m benchmarks.run_all

clean:
	rm -rf $(VENV) build *.egg-info web/node_modules
