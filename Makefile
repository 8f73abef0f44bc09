# Two entry points (see README): `make demo` and `make test`. Both create .venv on a fresh machine.
PY ?= python3
VENV := .venv
STAMP := $(VENV)/.installed-stamp
PYTEST_ARGS ?= -n 2 -q

.PHONY: setup demo test lint bench clean

$(STAMP): pyproject.toml
	@# headless Chromium renders the HTML benchmark report in its test (Debian package; root on CI machines)
	command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) || \
	  echo "note: chromium not installed; the report's browser test will be skipped"; }
	test -x $(VENV)/bin/python || $(PY) -m venv $(VENV)
	$(VENV)/bin/pip install -q --upgrade pip
	$(VENV)/bin/pip install -q -e '.[test,ray]'
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(VENV)/bin/aeroloc demo

# lint: ruff (lint + format) and the import layers (pyproject.toml [tool.importlinter]); part of `make test`
lint: setup
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/ruff format --check src tests benchmarks
	$(VENV)/bin/lint-imports

test: lint
	$(VENV)/bin/pytest $(PYTEST_ARGS)

clean:
	rm -rf $(VENV) out build *.egg-info src/*.egg-info
