# Every target creates .venv when missing: torch 2.13.0 (CPU) first, so that no other torch is
# pulled, then the project with its extras.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install test lint eval bench build-db serve clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev,service]'
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/pytest -q

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

eval: $(STAMP)
	$(BIN)/ds3d eval h36m --out docs/results/h36m.json

bench: $(STAMP)
	$(BIN)/ds3d bench lift

build-db: $(STAMP)
	$(BIN)/ds3d build-db --source h36m --out models/posedb

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache

serve: $(STAMP)
	$(BIN)/ds3d-serve --host 127.0.0.1 --port 8000
