# Set-up and the two jobs of the README. Every target creates .venv and installs the project first
# (once: the stamp is refreshed only when pyproject.toml or this file changes). torch==2.13.0 is
# pinned, so pip takes the CPU build already available to it and downloads no other torch.
PYTHON ?= python3.11
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: paper test test-float setup lint typecheck docs clean

paper: $(STAMP)
	$(VENV)/bin/factorq paper $(ARGS)

# The suite on this CPU's kernels, then its float-sensitive part (networks, Adam, DQN) again under
# two other kernel sets, as another machine would round (docs/decisions.md, "Tests that hold on
# any machine"). Where ARGS selects no float-sensitive test, pytest's "no tests" (exit 5) is fine.
# One pytest-xdist worker per core, idle workers stealing tests (TEST_WORKERS=0: in-process).
TEST_WORKERS ?= auto
XDIST := $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist worksteal)
test: $(STAMP)
	$(VENV)/bin/python -m pytest $(XDIST) $(ARGS)
	$(MAKE) --no-print-directory test-float

# The two kernel sets run at the same time, each in one process with half the cores' threads:
# a run of 40 tests, two of them long, keeps one process busy better than two workers, and only
# the files that mark a test float_sensitive are collected (ARGS naming tests selects instead).
FLOAT_FILES = $(shell grep -l float_sensitive tests/test_*.py)
FLOAT_SELECTION = $(if $(filter-out -%,$(ARGS)),$(ARGS),$(FLOAT_FILES) $(ARGS))
FLOAT_THREADS = $(shell $(VENV)/bin/python -c 'import os; print(max(1, (os.cpu_count() or 2) // 2))')
test-float: $(STAMP)
	@mkdir -p build; pids=; \
	for capability in default avx2; do \
	  ATEN_CPU_CAPABILITY=$$capability FACTORQ_TEST_THREADS=$(FLOAT_THREADS) \
	    $(VENV)/bin/python -m pytest -q -p no:cacheprovider -m float_sensitive $(FLOAT_SELECTION) \
	    > build/test-float-$$capability.log 2>&1 & pids="$$pids $$!"; \
	done; \
	set -- $$pids; failed=0; \
	for capability in default avx2; do \
	  wait $$1; code=$$?; shift; \
	  echo "float-sensitive tests under ATEN_CPU_CAPABILITY=$$capability"; \
	  cat build/test-float-$$capability.log; \
	  [ $$code -eq 0 ] || [ $$code -eq 5 ] || failed=$$code; \
	done; \
	exit $$failed

setup: $(STAMP)

# torch through pip, which reads pip's own configuration (where the local CPU wheel is found);
# the rest through uv (pinned), which resolves and installs the ~150 packages in seconds and
# compiles them in parallel, so that no interpreter of the suite compiles what it imports
# (docs/decisions.md, "CI time"). torch, installed by pip uncompiled, is compiled with the
# project's own modules. The torch pin is pyproject.toml's (tests/test_docs.py holds them equal).
# Where uv cannot reach an index that pip can (a private mirror named only in pip.conf), pip
# installs the same things: slower, the same result.
EXTRAS := .[dev,distributed,minigrid,highway,sb3,docs]
$(STAMP): pyproject.toml Makefile
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --no-compile torch==2.13.0 uv==0.13.9
	$(VENV)/bin/uv pip install --quiet --python $(VENV)/bin/python --compile-bytecode -e '$(EXTRAS)' \
	  || $(VENV)/bin/python -m pip install --quiet -e '$(EXTRAS)'
	$(VENV)/bin/python -m compileall -q -j 0 envs trainers factorq_torch
	$(VENV)/bin/python -m compileall -q -j 0 -x '/torch/testing/_internal/' \
	  "$$($(VENV)/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["platlib"])')/torch"
	touch $(STAMP)

lint: $(STAMP)
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

# mypy on the three packages under their installed names (pyproject's [tool.mypy] says how).
typecheck: $(STAMP)
	mkdir -p build/typecheck
	ln -sfn ../../envs build/typecheck/factorq_envs
	ln -sfn ../../trainers build/typecheck/factorq_trainers
	$(VENV)/bin/mypy

# The documentation site (mkdocs.yml) into build/site; warnings are errors. The docs extra is
# installed by the set-up, so the tests that need it (griffe's doctest fencing) run everywhere.
docs: $(STAMP)
	$(VENV)/bin/mkdocs build --strict

clean:
	rm -rf $(VENV) build *.egg-info
