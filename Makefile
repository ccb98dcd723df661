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

# The tests' scratch folders (stores, the S3 server's and clusters' files: about 90,000 files
# and 0.6 GB a run) in memory where /dev/shm is a tmpfs with room (tests/scratch_dir.sh), only
# the last run's kept (0.3-0.6 GB of memory until the next): on a disk (ext4) creating and
# deleting them cost 15% of the run (3m24-3m35 against 3m41-4m15 on 2 cores). Deleting each
# passed test's folder as it ends (tmp_path_retention_policy=failed) measured 3m42-3m45.
# TEST_TMPDIR=DIR puts them in DIR; TEST_TMPDIR= in the system's temporary folder.
TEST_TMPDIR ?= auto

test: $(STAMP)
	$(BIN)/ruff check .
	scratch=$$(sh tests/scratch_dir.sh "$(TEST_TMPDIR)"); \
	  TMPDIR="$${scratch:-$$TMPDIR}" $(BIN)/pytest -n $(TEST_WORKERS) --dist loadfile \
	    -o tmp_path_retention_count=1

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
