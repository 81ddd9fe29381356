# make setup | serve | test | bench | lint | soak: each does whatever set-up is still missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.uacell-installed
NODE_STAMP := interop/node_modules/.uacell-installed

.PHONY: setup serve test bench lint clean models soak browser postgresql mosquitto screenshots bytecode

setup: $(STAMP) models $(NODE_STAMP) browser postgresql mosquitto bytecode

# uacell's modules compiled once, as pip compiles an installed package's: a start then reads them
# instead of compiling them (90 ms of each start here), also where PYTHONDONTWRITEBYTECODE is set.
# Only what changed since is compiled again; a stale file is never used (Python checks the source).
bytecode: $(STAMP)
	@$(BIN)/python -m compileall -q src benchmarks tools >/dev/null

# Chromium for the web HMI's browser tests (Playwright drives it; it never downloads a browser).
browser:
	@if command -v chromium >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		echo "installing Debian's chromium for the browser tests"; \
		{ apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } \
		|| echo "make setup: could not install chromium, so the web HMI's browser tests will be skipped"; \
	else \
		echo "make setup: chromium is missing, so the web HMI's browser tests will be skipped (as root: apt-get install chromium)"; \
	fi

# Debian's PostgreSQL for the history store's second backend (its tests start their own cluster).
postgresql:
	@if command -v initdb >/dev/null 2>&1 || ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		echo "installing Debian's postgresql for the history tests"; \
		{ apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql >/dev/null; } \
		|| echo "make setup: could not install postgresql, so the PostgreSQL history tests will be skipped"; \
	else \
		echo "make setup: postgresql is missing, so the PostgreSQL history tests will be skipped (as root: apt-get install postgresql)"; \
	fi

# Debian's mosquitto for the PubSub tests and benchmarks (they start their own brokers on free ports).
mosquitto:
	@if command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ]; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		echo "installing Debian's mosquitto for the PubSub tests"; \
		{ apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto mosquitto-clients >/dev/null \
		  && { systemctl disable --now mosquitto >/dev/null 2>&1 || service mosquitto stop >/dev/null 2>&1 || true; }; } \
		|| echo "make setup: could not install mosquitto, so the PubSub tests will be skipped"; \
	else \
		echo "make setup: mosquitto is missing, so the PubSub tests will be skipped (as root: apt-get install mosquitto mosquitto-clients)"; \
	fi

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[all,test]'  # every extra: the tests use them all
	@touch $@

models: $(STAMP)
	$(BIN)/uacell models fetch

$(NODE_STAMP): interop/package.json interop/package-lock.json
	cd interop && npm ci --no-audit --no-fund --loglevel=error
	@touch $@

serve: $(STAMP) models bytecode
	$(BIN)/uacell serve $(ARGS)

# Three workers, each taking whole test files (their module fixtures start servers once): the suite
# waits on servers, PLCs and browsers more than it computes. On two cores, two workers kept 1.45 of
# them busy (11:46) and three 1.74 (9:34), four no faster (9:23). PYTEST_ARGS="-n 0": one process.
PYTEST_ARGS ?= -n 3 --dist loadfile

test: setup
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)

# Every section, the 20-minute soak included; one of them: ARGS="--only soak --minutes 2" (docs/performance.md).
bench: setup
	$(BIN)/python -m benchmarks $(ARGS)

# Renew the pictures in docs/ from the headless-browser tests.
screenshots: setup
	UACELL_SCREENSHOTS=docs $(BIN)/python -m pytest -q tests/test_web_browser.py

# Not part of `make test`: 200 sessions with subscriptions for 10 minutes while the cell cycles;
# reports the server's RSS growth and lost notifications (SOAK_ARGS="--sessions 50 --minutes 2").
# The mixed-load soak with targets is a section of `make bench` (--only soak).
soak: setup
	$(BIN)/python tools/soak.py $(SOAK_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) interop/node_modules
