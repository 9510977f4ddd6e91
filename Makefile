# Every target creates .venv when missing: torch 2.13.0 (CPU) first, so that no other torch is
# pulled, then the project with its extras. PyPI's torch wheel for Linux is the CUDA build: the CPU
# one comes from PyTorch's index (TORCH_INDEX), tried once (--retries 0), so that where it cannot be
# reached pip goes on at once with the wheels it can see (PyPI, a local wheelhouse).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu

.PHONY: install test lint audit eval bench build-db serve clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet --retries 0 --extra-index-url $(TORCH_INDEX) torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev,service]'
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/pytest -q

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# Known vulnerabilities of the installed dependencies; the last result is kept in docs/security/.
audit: $(STAMP)
	mkdir -p docs/security
	$(BIN)/pip-audit --skip-editable --progress-spinner off -f json -o docs/security/pip-audit.json

eval: $(STAMP)
	$(BIN)/ds3d eval h36m --threads 1 --variants clean --out docs/results/h36m.json

bench: $(STAMP)
	$(BIN)/ds3d bench lift

build-db: $(STAMP)
	$(BIN)/ds3d build-db --source h36m --out models/posedb

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache

serve: $(STAMP)
	$(BIN)/ds3d-serve --host 127.0.0.1 --port 8000
