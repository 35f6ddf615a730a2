# Task runner: the targets CI calls (`lint`, `test`) and the ones people type.
SHELL := bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

PYTHON ?= python3
VENV := .venv
VENV_STAMP := $(VENV)/.installed
CARGO ?= cargo

.PHONY: help venv test test-unit lint fmt bench build clean

help: ## List the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-10s %s\n", $$1, $$2}'

$(VENV_STAMP): tests/requirements.txt
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check -r tests/requirements.txt
	touch $@

venv: $(VENV_STAMP) ## Install the emulators (pinned moto[server]) into .venv

test: venv ## The whole suite, emulator tests included (README's and CI's command)
	$(CARGO) test --workspace --all-targets -- --include-ignored
	$(CARGO) test --workspace --doc

test-unit: ## Tests that need nothing but cargo (what plain `cargo test` runs)
	$(CARGO) test --workspace

lint: ## rustfmt check and clippy with warnings as errors
	$(CARGO) fmt --all --check
	$(CARGO) clippy --workspace --all-targets -- -D warnings

fmt: ## Format the code
	$(CARGO) fmt --all

bench: ## Merge benchmark on the 1024-route fixture (targets: 5 ms in-process, 15 ms process)
	$(CARGO) bench -p sidecar --bench merge

build: ## Release build of every binary
	$(CARGO) build --workspace --release

clean: ## Remove build output and the venv
	$(CARGO) clean
	rm -rf $(VENV)
