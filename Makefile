# The two commands a new user needs (each installs what it needs first, idempotently):
#   make demo   - the end-to-end demo
#   make test   - the whole test suite
# Everything the build needs from outside lands in third_party/ (gitignored).

CARGO ?= cargo
PYTHON ?= python3

.PHONY: demo test setup bench fmt lint

setup:
	$(PYTHON) scripts/fetch_libtorch.py
	$(PYTHON) scripts/fetch_mujoco.py

demo: setup
	$(CARGO) run --release -p promptdt -- demo

test: setup
	$(CARGO) test --release --workspace

# Side-by-side with PyTorch (needs a Python with torch 2.11: see scripts/requirements-torch.txt).
bench: setup
	$(CARGO) run --release -p promptdt -- bench --python $(or $(TORCH_PYTHON),.venv/bin/python) --out target/bench

fmt:
	$(CARGO) fmt --all

lint:
	$(CARGO) clippy --release --workspace --all-targets -- -D warnings
