# Every target creates .venv with python3 -m venv and installs the project when needed,
# pinned to constraints.txt (the versions the suite was last green with).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
LATEST := .venv-latest

.PHONY: demo test bench clean test-latest lock

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt --upgrade pip
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/calib demo --out demo-out

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python -m bench

# The suite against the newest release of every dependency (no constraints): tells whether
# the lock can move forward. Prints the versions that differ from constraints.txt.
test-latest:
	rm -rf $(LATEST)
	$(PY) -m venv $(LATEST)
	$(LATEST)/bin/python -m pip install --quiet --disable-pip-version-check --upgrade pip
	$(LATEST)/bin/python -m pip install --quiet --disable-pip-version-check -e '.[test]'
	$(LATEST)/bin/python -m pip freeze --exclude-editable | sort -f > $(LATEST)/freeze.txt
	@echo "versions that differ from constraints.txt (< locked, > newest):"
	@grep -v '^#' constraints.txt | grep -v '^pip==' | sort -f | diff - $(LATEST)/freeze.txt || true
	$(LATEST)/bin/python -m pytest -q

# Move the lock to the newest versions, only if the suite passes on them.
lock: test-latest
	{ sed -n '/^#/p' constraints.txt; $(LATEST)/bin/python -m pip freeze --all --exclude-editable \
	  | grep -E '^pip=='; cat $(LATEST)/freeze.txt; } > constraints.txt.new
	mv constraints.txt.new constraints.txt
	@echo "constraints.txt updated; commit it with the test run's result"

clean:
	rm -rf $(VENV) $(LATEST) demo-out
