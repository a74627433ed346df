# The two set-up commands of the README: `make demo` and `make test`.
PY := .venv/bin/python

.PHONY: install demo test lint typecheck openapi bench clean frontend

install:
	bash scripts/install.sh

demo: install
	.venv/bin/dancegraph quickstart

test: install
	$(PY) -m pytest -q

lint:
	.venv/bin/ruff check .
	.venv/bin/ruff format --check .

typecheck:
	.venv/bin/mypy

frontend:
	bash scripts/install-frontend.sh

openapi:
	$(PY) scripts/export_openapi.py

bench: install
	$(PY) -m bench

clean:
	rm -rf var out .pytest_cache
