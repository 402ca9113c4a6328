# Set-up and the two jobs of the README. Every target creates .venv and installs the project first
# (once: the stamp is refreshed only when pyproject.toml or this file changes). torch==2.13.0 is
# pinned, so pip takes the CPU build already available to it and downloads no other torch.
PYTHON ?= python3.11
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: paper test test-float setup lint typecheck docs clean

paper: $(STAMP)
	$(VENV)/bin/factorq paper $(ARGS)

# The suite on this CPU's kernels in a shuffled order (pytest-randomly prints its seed: replay
# with ARGS="--randomly-seed=N", keep the file order with ARGS="-p no:randomly"), then its
# float-sensitive part (networks, Adam, DQN) again under another kernel set, as another machine
# would round (docs/decisions.md, "Tests that hold on any machine"). Where ARGS selects no float-sensitive test, pytest's "no tests" (exit 5) is fine.
# One pytest-xdist worker per core, idle workers stealing tests (TEST_WORKERS=0: in-process).
TEST_WORKERS ?= auto
XDIST := $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist worksteal)
test: $(STAMP)
	$(VENV)/bin/python -m pytest $(XDIST) $(ARGS)
	$(MAKE) --no-print-directory test-float

# Only the files that mark a test float_sensitive are collected (ARGS naming tests selects
# instead). One foreign kernel set, `default` (no vector instructions: the rounding furthest from
# any vector unit's), skipped where it is this CPU's own (docs/decisions.md, "CI time").
FLOAT_FILES = $(shell grep -l float_sensitive tests/test_*.py)
FLOAT_SELECTION = $(if $(filter-out -%,$(ARGS)),$(ARGS),$(FLOAT_FILES) $(ARGS))
NATIVE_CAPABILITY = $(shell $(VENV)/bin/python -c \
  'import torch; print(torch.backends.cpu.get_cpu_capability().lower())')
test-float: $(STAMP)
	@native=$(NATIVE_CAPABILITY); \
	if [ "$$native" = default ]; then \
	  echo "float-sensitive tests under default: this CPU's own kernels, run above"; exit 0; \
	fi; \
	echo "float-sensitive tests under ATEN_CPU_CAPABILITY=default (this CPU's own: $$native)"; \
	ATEN_CPU_CAPABILITY=default $(VENV)/bin/python -m pytest -q -p no:cacheprovider \
	  $(XDIST) -m float_sensitive $(FLOAT_SELECTION); \
	code=$$?; [ $$code -eq 0 ] || [ $$code -eq 5 ] || exit $$code

setup: $(STAMP)

# torch through pip, which reads pip's own configuration (where the local CPU wheel is found);
# the rest through uv (pinned), which resolves and installs the ~150 packages in seconds and
# compiles them in parallel, so that no interpreter of the suite compiles what it imports
# (docs/decisions.md, "CI time"). What pip installs (torch and its requirements: sympy, imported
# by torch._dynamo whenever tensordict is, ~2 s to compile in every process) is left uncompiled
# by pip and compiled in parallel before uv adds the rest (once: skipped where torch and sympy
# are compiled already). The torch pin is pyproject.toml's (tests/test_docs.py holds them equal).
# Where uv cannot reach an index that pip can (a private mirror named only in pip.conf), pip
# installs the same things: slower, the same result.
#
# The project is installed in setuptools' strict editable mode (issue 38): a tree of links to the
# source files, build/__editable__.*, on sys.path through a plain .pth entry, so plain mypy (and any
# tool that reads sys.path without running import hooks) finds factorq_envs and factorq_trainers
# from a user's script; the default mode's import hook hides them from mypy. The tree holds one link
# per file, so the list of source files ($(FILES), rewritten only when it changes) is a
# prerequisite: a file added or removed re-runs the set-up (everything else already there: seconds).
# The list is written to a file of this make's own (its shell's PID): CI runs two makes at once.
EXTRAS := .[dev,distributed,minigrid,highway,sb3,docs]
FILES := $(VENV)/.factorq-files
$(shell mkdir -p $(VENV) && find envs trainers factorq_torch -type f -not -path '*/__pycache__/*' \
  | LC_ALL=C sort > $(FILES).$$$$ && { cmp -s $(FILES).$$$$ $(FILES) || mv $(FILES).$$$$ $(FILES); }; \
  rm -f $(FILES).$$$$)
$(STAMP): pyproject.toml Makefile $(FILES)
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --no-compile torch==2.13.0 uv==0.13.9
	site="$$($(VENV)/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["platlib"])')"; \
	ls "$$site"/torch/__pycache__/__init__.*.pyc "$$site"/sympy/__pycache__/__init__.*.pyc \
	  > /dev/null 2>&1 \
	  || $(VENV)/bin/python -m compileall -q -j 0 -x '/torch/testing/_internal/' "$$site"
	$(VENV)/bin/uv pip install --quiet --python $(VENV)/bin/python --compile-bytecode \
	  --config-setting editable_mode=strict --reinstall-package factorq-torch -e '$(EXTRAS)' \
	  || $(VENV)/bin/python -m pip install --quiet --config-settings editable_mode=strict \
	     -e '$(EXTRAS)'
	$(VENV)/bin/python -m compileall -q -j 0 envs trainers factorq_torch build/__editable__.*
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
