# Two entry points: `make demo` and `make test`. Both create or refresh .venv first.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv bench clean browser

$(STAMP): pyproject.toml web/package-lock.json
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "make: $(PYTHON) not found (Python 3.11+ is required)"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	cd web && npm ci --no-audit --no-fund --loglevel=error  # the web client's decoder (fzstd), served offline
	touch $(STAMP)

# The browser the web client's tests drive (playwright's Python API with Debian's chromium, no download).
browser:
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && apt-get update -q && apt-get install -y -q chromium; } \
		|| echo "make: chromium is not installed and this is not root: the browser tests will skip"

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/psao demo

test: $(STAMP) browser
	$(BIN)/python -m pytest -q -ra

bench: $(STAMP)
	$(BIN)/python -m benchmarks.run_all

clean:
	rm -rf $(VENV) build *.egg-info web/node_modules
