# photonfarm: every target sets itself up on a fresh machine (Python 3.11+ with venv).
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: serve test bench clean

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,bench]'
	touch $(STAMP)

# The API on :8000 with an embedded Redis (data in ./data) and one worker per core.
serve: $(STAMP)
	$(VENV)/bin/photonfarm serve --host 127.0.0.1 --port 8000

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) -m bench.run_all

clean:
	rm -rf $(VENV) out
