# Every target creates .venv when missing: torch 2.13.0 (CPU) first, so that no other torch is
# pulled, then the locked dependencies, then the project. PyPI's torch wheel for Linux is the CUDA
# build: the CPU one comes from PyTorch's index (TORCH_INDEX), tried once (--retries 0), so that
# where it cannot be reached pip goes on at once with the wheels it can see (PyPI, a local
# wheelhouse).
# The locks in requirements/ pin every other package, with its hashes, for Python 3.11 on Linux
# x86_64: dev.txt (runtime, [service], [dev]; installed here), service.txt (runtime, [service]; the
# Docker image), ray.txt (runtime, [service], [ray]; added by .ci/run, or the Ray image).
# `make lock` refreshes them from pyproject.toml's ranges (which stay what other installs of the
# library see); the project itself is installed with --no-deps, so nothing unlocked comes in.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
PIP_TOOLS := pip-tools==7.6.2
LOCKS := requirements/dev.txt requirements/service.txt requirements/ray.txt

.PHONY: install lock test test-fast lint audit eval floors check-results bench build-db serve clean

$(STAMP): pyproject.toml requirements/dev.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet --retries 0 --extra-index-url $(TORCH_INDEX) torch==2.13.0
	$(BIN)/pip install --quiet --require-hashes -r requirements/dev.txt
	$(BIN)/pip install --quiet --no-deps -e .
	$(BIN)/pip check
	touch $(STAMP)

install: $(STAMP)

# Resolves afresh, to the newest versions that pyproject.toml's ranges allow, against torch's CPU
# build (requirements/torch.txt), and leaves torch out of the locks. service.txt and ray.txt are
# constrained by dev.txt, so that a package has one version in all three.
PIP_COMPILE := CUSTOM_COMPILE_COMMAND="make lock" $(BIN)/pip-compile --quiet --upgrade \
	--generate-hashes --strip-extras --no-emit-index-url --no-emit-find-links \
	--unsafe-package torch -c requirements/torch.txt \
	--extra-index-url $(TORCH_INDEX) --pip-args --retries=0

lock:
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet $(PIP_TOOLS)
	$(PIP_COMPILE) --extra service --extra dev -o requirements/dev.txt pyproject.toml
	$(PIP_COMPILE) -c requirements/dev.txt --extra service \
		-o requirements/service.txt pyproject.toml
	$(PIP_COMPILE) -c requirements/dev.txt --extra service --extra ray \
		-o requirements/ray.txt pyproject.toml
	! grep -iE '^(torch|triton|nvidia-)' $(LOCKS)

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/pytest -q

# The quick loop: the suite without the tests marked slow (pyproject.toml's markers).
test-fast: $(STAMP)
	$(BIN)/pytest -q -m "not slow"

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

# Known vulnerabilities of the installed dependencies; the last result is kept in docs/security/.
audit: $(STAMP)
	mkdir -p docs/security
	$(BIN)/pip-audit --skip-editable --progress-spinner off -f json -o docs/security/pip-audit.json

eval: $(STAMP)
	$(BIN)/ds3d eval h36m --threads 1 --variants clean --out docs/results/h36m.json

# The figures the accuracy tests compare with, recorded again after a change that moves them on
# purpose: LSP test into the model's manifest (tests/image2d/test_accuracy.py), Human3.6M as
# `make eval` (tests/test_lifter.py), finding people on 24 canvases (tests/evaluation/test_people.py).
floors: eval
	$(BIN)/ds3d --quiet eval lsp --write-manifest
	$(BIN)/ds3d --quiet eval people --count 24 --out docs/results/people-24.json

# The at-a-glance figures of docs/RESULTS.md and docs/service-results.md against the JSON reports
# their rows name: each the report's value, the report with its provenance (tools/check_results.py).
check-results: $(STAMP)
	$(BIN)/python -m tools.check_results

bench: $(STAMP)
	$(BIN)/ds3d bench lift

build-db: $(STAMP)
	$(BIN)/ds3d build-db --source h36m --out models/posedb

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache

serve: $(STAMP)
	$(BIN)/ds3d-serve --host 127.0.0.1 --port 8000
