# photonfarm: every target sets itself up on a fresh machine (Python 3.11+ with venv).
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: serve test bench clean deps

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,bench]'
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

bench: $(STAMP)
	$(PY) -m bench.run_all

clean:
	rm -rf $(VENV) out
