# The two set-up commands of the README: `make demo` and `make test`.
PY := .venv/bin/python

.PHONY: install demo test lint openapi bench clean frontend

install:
	bash scripts/install.sh

demo: install
	$(PY) -m dancegraph.cli quickstart

test: install
	$(PY) -m pytest -q

lint:
	.venv/bin/ruff check .
	.venv/bin/ruff format --check .

frontend:
	bash scripts/install-frontend.sh

openapi:
	$(PY) scripts/export_openapi.py

bench: install
	$(PY) -m bench

clean:
	rm -rf var out .pytest_cache
