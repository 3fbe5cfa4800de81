# The two commands of the README:
#   make demo   set everything up, then run the scripted demo (no CAN hardware, no root)
#   make test   set everything up, then run every test (CI runs exactly this: .ci/run)
PYTHON ?= python3
VENV   := .venv
VPY    := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
COVDIR := build/cov

.PHONY: setup demo test check coverage hil bench mutants mcu clean install
setup: $(STAMP) $(VENV)/bin/estopd

$(STAMP): pyproject.toml setup.py pyext/build_core.py deps/debian-packages.txt $(wildcard firmware/core/*)
	scripts/ensure-debs build
	test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip
	$(VPY) -m pip install -q -e '.[test]'
	touch $@

$(VENV)/bin/estopd: $(STAMP) $(wildcard firmware/core/* firmware/estopd/*)
	$(MAKE) -C firmware
	install -m 0755 firmware/build/estopd $@

demo: setup
	$(VENV)/bin/estop demo

test: setup
	$(MAKE) check
	$(MAKE) coverage
	$(MAKE) hil

check: setup
	scripts/ensure-debs check
	$(MAKE) -C firmware strict
	$(VENV)/bin/ruff check src tests hil bench pyext tools

# The whole suite runs once against a build of the core instrumented for gcov and UBSan
# (UB aborts the process), then the spec vectors run again on the installed optimised build.
# The MCU tests (tests/test_mcu_*.py) build the core for Cortex-M and need the toolchain.
coverage: setup
	scripts/ensure-debs mcu
	rm -rf $(COVDIR) && mkdir -p $(COVDIR)
	$(VPY) pyext/build_instrumented.py $(COVDIR)
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" PYTHONPATH=$(COVDIR) ESTOP_CORE_MODULE=_estop_core_cov \
	  UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 $(VPY) -m pytest -q
	$(VENV)/bin/gcovr --root . --filter 'firmware/core/' --object-directory $(COVDIR) \
	  --txt-metric branch --print-summary --fail-under-line 100 $(COVDIR)
	$(VPY) -m pytest -q tests/test_spec_vectors.py

hil: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" hil/run

# Benchmarks (not part of `make test`): stop latency vs the asyncio baseline, memory soak,
# instructions per input (host and Cortex-M). Reports land in bench/out/.
bench: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VPY) bench/stop_latency.py
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VPY) bench/rss_soak.py
	$(VPY) bench/core_instructions.py
	scripts/ensure-debs mcu
	$(VPY) bench/mcu_instructions.py

# The core on Cortex-M0+ and M4 (-Os, -O2) under build/mcu/: footprint, stack per entry point,
# instructions per call in the emulator, checked against the budget (docs/MCU.md).
mcu: setup
	scripts/ensure-debs mcu
	$(VPY) tools/mcu/report.py

# Mutation testing of the core (about 1.5 minutes; not part of `make test`).
mutants: setup
	$(VPY) tools/mutants.py

clean:
	rm -rf build firmware/build $(VENV) src/estop/_core*.so

# Installation on a car (README: "Run it on a car"). PREFIX and SYSCONFDIR as usual; DESTDIR
# for staging. A key is made only where none exists (never overwritten), mode 0600; the same
# for the config. Then: systemctl daemon-reload && systemctl enable --now estopd.
PREFIX     ?= /usr/local
SYSCONFDIR ?= /etc
BINDIR     := $(PREFIX)/bin
UNITDIR    ?= $(PREFIX)/lib/systemd/system
DOCDIR     := $(PREFIX)/share/doc/estop
install: firmware/build/estopd
	install -D -m 0755 firmware/build/estopd $(DESTDIR)$(BINDIR)/estopd
	install -d -m 0755 $(DESTDIR)$(UNITDIR) $(DESTDIR)$(DOCDIR)
	sed -e 's|@BINDIR@|$(BINDIR)|g' -e 's|@SYSCONFDIR@|$(SYSCONFDIR)|g' -e 's|@DOCDIR@|$(DOCDIR)|g' \
	  deploy/estopd.service.in > $(DESTDIR)$(UNITDIR)/estopd.service
	chmod 0644 $(DESTDIR)$(UNITDIR)/estopd.service
	install -m 0644 docs/PROTOCOL.md deploy/estopd.conf.example $(DESTDIR)$(DOCDIR)/
	install -d -m 0700 $(DESTDIR)$(SYSCONFDIR)/estop
	test -e $(DESTDIR)$(SYSCONFDIR)/estop/estopd.conf || \
	  install -m 0644 deploy/estopd.conf.example $(DESTDIR)$(SYSCONFDIR)/estop/estopd.conf
	test -e $(DESTDIR)$(SYSCONFDIR)/estop/key || scripts/new-key $(DESTDIR)$(SYSCONFDIR)/estop/key

firmware/build/estopd: $(wildcard firmware/core/* firmware/estopd/*)
	$(MAKE) -C firmware
