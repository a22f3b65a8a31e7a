# The two commands a new user needs (each installs what it needs first, idempotently):
#   make demo   - the end-to-end demo
#   make test   - the whole test suite
# Everything the build needs from outside lands in third_party/ (gitignored).

CARGO ?= cargo
PYTHON ?= python3
# A Python with torch 2.11.0 (scripts/setup_torch_venv.sh installs one in .venv). When it is there,
# `make test` first makes the PyTorch parity fixtures on this machine, and the parity tests then
# compare against them bit for bit (besides the committed fixtures, within cross-CPU bounds).
TORCH_PYTHON ?= .venv/bin/python
LIVE_GOLDEN := target/golden-live

.PHONY: demo test test-other-kernels setup setup-render bench fmt lint torch-venv live-golden python python-test

setup:
	$(PYTHON) scripts/fetch_libtorch.py
	$(PYTHON) scripts/fetch_mujoco.py
	$(PYTHON) scripts/fetch_metaworld.py

# EGL and Mesa for the rendering tests (docs/rendering.md): installed with apt-get where missing.
setup-render:
	bash scripts/setup_render.sh

demo: setup
	$(CARGO) run --release -p promptdt -- demo

# The reference release's data (its 42 prompt files and task parameters) sits at ../shared/data
# beside the checkout in CI, or where PROMPTDT_REFERENCE_DATA points. A clone without it skips the
# tests that read it (each appends its name to REFERENCE_SKIPS), and the list is printed once after
# the run. CI sets PROMPTDT_REQUIRE_REFERENCE_DATA=1, which makes a missing directory a failure.
# The environment worker's tests, which need a Python with promptdt and gymnasium, log their skips
# there too; `make python-test` then runs them against the venv it builds.
REFERENCE_SKIPS := target/reference-data-skipped.txt

# --no-fail-fast: every test binary runs even when one fails, so a failure report is complete.
# OMP_WAIT_POLICY=PASSIVE: tests run side by side, each with libtorch threads; spinning OpenMP
# threads then slow everything down many times over (results do not depend on it).
test: setup setup-render live-golden
	@rm -f $(REFERENCE_SKIPS)
	@echo "$(CARGO) test --release --workspace --no-fail-fast"
	@status=0; OMP_WAIT_POLICY=$${OMP_WAIT_POLICY:-PASSIVE} PROMPTDT_LIVE_GOLDEN=$(abspath $(LIVE_GOLDEN)) PROMPTDT_REFERENCE_SKIP_LOG=$(abspath $(REFERENCE_SKIPS)) $(CARGO) test --release --workspace --no-fail-fast || status=$$?; \
	if [ -s $(REFERENCE_SKIPS) ]; then \
		echo; \
		echo "note: $$(sort -u $(REFERENCE_SKIPS) | wc -l) tests skipped what they need from outside (the whole test, or the part that needs it; each line says what):"; \
		echo "  the reference release's data, looked for at $${PROMPTDT_REFERENCE_DATA:-../shared/data} (PROMPTDT_REFERENCE_DATA=DIR;"; \
		echo "  docs/reproduce.md, 'Reference data'), or a Python with promptdt and gymnasium (PROMPTDT_PYTHON; make python)."; \
		sort -u $(REFERENCE_SKIPS) | sed 's/^/  - /'; \
	fi; \
	exit $$status

# The tests that compare with numbers committed from another machine, again on another kernel path
# of libtorch (scripts/test_other_kernels.sh): a bitwise assumption against another CPU's numbers
# then fails on any CPU, not only on a user's. CI runs it after `make test`.
test-other-kernels: setup
	bash scripts/test_other_kernels.sh

live-golden:
	@rm -rf $(LIVE_GOLDEN)
	@if $(TORCH_PYTHON) -c "import torch" 2>/dev/null; then \
		$(TORCH_PYTHON) scripts/golden/make_prompt_dt_fixtures.py --out $(LIVE_GOLDEN) --threads 1 && \
		$(TORCH_PYTHON) scripts/golden/make_macaw_fixtures.py --out $(LIVE_GOLDEN) --threads 1; \
	else \
		echo "no torch at $(TORCH_PYTHON): bitwise parity against PyTorch on this CPU skipped (make torch-venv)"; \
	fi

torch-venv:
	bash scripts/setup_torch_venv.sh

# The Python package (docs/python.md): build the wheel, install it into PY_VENV, run its tests.
PY_VENV ?= .venv-promptdt
python:
	bash scripts/install_python.sh $(PY_VENV)

python-test:
	PROMPTDT_PY_EXTRAS=minari bash scripts/install_python.sh $(PY_VENV)
	# The promptdt command, for the tests that drive it (examples/pendulum_tasks by the README's
	# commands, reproduce): nothing to build after `make test` (CI), which built it already.
	$(CARGO) build --release -p promptdt
	OMP_WAIT_POLICY=$${OMP_WAIT_POLICY:-PASSIVE} $(PY_VENV)/bin/python -m pytest -q crates/python/pytests
	# The environment worker's Rust tests (gymnasium through `python -m promptdt.worker`), against
	# the venv just built: `make test` skips them where no such Python is found.
	PROMPTDT_PYTHON=$(abspath $(PY_VENV))/bin/python PROMPTDT_REQUIRE_WORKER_PYTHON=1 $(CARGO) test --release -p pdt-envs --test it -- worker:: collect_policy::
	# `promptdt data import --minari` and `promptdt collect --policy` (through that Python), each
	# against Python's own.
	PROMPTDT_PYTHON=$(abspath $(PY_VENV))/bin/python PROMPTDT_REQUIRE_WORKER_PYTHON=1 $(CARGO) test --release -p promptdt --test it -- import_flat:: collect_suite::

# Side-by-side with PyTorch (needs a Python with torch 2.11: see scripts/requirements-torch.txt).
bench: setup
	$(CARGO) run --release -p promptdt -- bench --python $(or $(TORCH_PYTHON),.venv/bin/python) --out target/bench

fmt:
	$(CARGO) fmt --all

lint:
	$(CARGO) clippy --release --workspace --all-targets -- -D warnings
