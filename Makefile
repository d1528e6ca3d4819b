# The two commands of the README's Quickstart, `make lint` and `make docs`. All set up .venv on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Optional package index for torch alone, e.g. the CPU-only builds:
#   make setup TORCH_INDEX=https://download.pytorch.org/whl/cpu
TORCH_INDEX ?=

.PHONY: demo test lint docs setup clean

setup: $(STAMP)

$(STAMP): pyproject.toml deploy/constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(if $(TORCH_INDEX),$(PY) -m pip install --quiet -c deploy/constraints.txt --index-url $(TORCH_INDEX) torch)
	$(PY) -m pip install --quiet -c deploy/constraints.txt -e ".[dev,onnx,ros,coco,docs]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/branchrange demo --out out/demo

test: $(STAMP)
	$(PY) -m pytest -q

# ruff (settings in pyproject.toml) on the whole tree; mypy on the typed core listed in [tool.mypy] files.
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

# The manual in site/ (mkdocs.yml); --strict turns a broken link, a missing page or a docstring warning into a failure.
docs: $(STAMP)
	$(VENV)/bin/mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) out site
