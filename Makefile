# The two set-up commands of the README. Both work alone on a fresh clone.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test clean

run: $(STAMP)
	$(BIN)/btf run configs/demo.yaml

# The test files on pytest workers (pytest-xdist), a file's tests on one worker so that its
# module fixtures are made once; TEST_WORKERS=0 runs them in this process. One worker more
# than cores: the tests' processes wait a fifth of their time on the processes, servers and
# I/O threads they start (2 cores: 2 workers 3m51-4m56, 3 workers 3m08, 4 workers 3m21).
TEST_WORKERS ?= $(shell $(PYTHON) -c 'import os; print((os.cpu_count() or 1) + 1)')

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/pytest -n $(TEST_WORKERS) --dist loadfile

# (Re)install when the package metadata changes; the stamp makes repeated runs instant.
# The [mitsuba] extra: make run's report shows the demo's tile set rendered by Mitsuba 3.
$(STAMP): pyproject.toml Makefile
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "Python 3.11+ is needed (found " + sys.version.split()[0] + "); set PYTHON=python3.11")'
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,mitsuba]'
	touch $(STAMP)

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
