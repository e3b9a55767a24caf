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

# Until the service lands, `make serve` renders a bundled scene locally.
serve: $(STAMP)
	mkdir -p out
	$(VENV)/bin/photonfarm render cornell-caustics --seconds 60 --out out/cornell-caustics.png

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) -m bench.run_all

clean:
	rm -rf $(VENV) out
