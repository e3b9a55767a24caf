# photonfarm: every target sets itself up on a fresh machine (Python 3.11+ with venv).
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: serve test bench clean deps lint docs docs-build

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,bench,lint,docs]'
	$(MAKE) --no-print-directory deps
	touch $(STAMP)

# The wheel's PoCL (LLVM 14) cannot compile for CPUs newer than it knows; Debian's
# pocl-opencl-icd is then installed beside it (kernels/program.py picks the device that builds).
deps:
	@$(PY) -c 'from kernels.program import create_context; create_context()' 2>/dev/null \
	    || { command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ] \
	         && (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq pocl-opencl-icd) >/dev/null \
	         && $(PY) -c 'from kernels.program import create_context; create_context()'; } \
	    || { $(PY) -c 'from kernels.program import create_context; create_context()'; exit 1; }

# The API on :8000 with an embedded Redis (data in ./data) and one worker per core.
serve: $(STAMP)
	$(VENV)/bin/photonfarm serve --host 127.0.0.1 --port 8000

test: $(STAMP)
	$(PY) -m pytest -q

# ruff (rules in pyproject.toml) over the tree, mypy over worker/, service/ and kernels/.
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

# The documentation site on :8001 (mkdocs.yml, docs/), and its strict build (as CI runs it).
docs: $(STAMP)
	$(VENV)/bin/mkdocs serve --dev-addr 127.0.0.1:8001

docs-build: $(STAMP)
	$(VENV)/bin/mkdocs build --strict --site-dir $(or $(SITE),site)

bench: $(STAMP)
	$(PY) -m bench.run_all

clean:
	rm -rf $(VENV) out
