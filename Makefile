# Task runner: the targets CI calls (`lint`, `test`) and the ones people type.
SHELL := bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

PYTHON ?= python3
VENV := .venv
VENV_STAMP := $(VENV)/.installed
CARGO ?= cargo

.PHONY: help venv lint-venv real-kube rehearse-upgrade kubernetes-support test test-unit lint fmt bench build clean sidecar bench-sidecar bench-latency bench-scale local bench-stack bench-functions deploy deploy-function rollback cluster cluster-manifests

help: ## List the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-14s %s\n", $$1, $$2}'

$(VENV_STAMP): tests/requirements.txt
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check -r tests/requirements.txt
	touch $@

venv: $(VENV_STAMP) ## Install the emulators (pinned moto[server]) into .venv

LINT_VENV := .venv-lint
LINT_STAMP := $(LINT_VENV)/.installed

$(LINT_STAMP): tests/lint-requirements.txt
	$(PYTHON) -m venv $(LINT_VENV)
	$(LINT_VENV)/bin/pip install --quiet --disable-pip-version-check -r tests/lint-requirements.txt
	touch $@

lint-venv: $(LINT_STAMP) ## Install the policy linters (pinned checkov, parliament) into .venv-lint

.PHONY: kubectl
kubectl: ## Install kubectl (Debian's kubernetes-client) when it is missing
	@command -v kubectl >/dev/null || { sudo=; [ "$$(id -u)" = 0 ] || sudo=sudo; \
		$$sudo apt-get update -qq && \
		$$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq kubernetes-client; }

.PHONY: ui-tools
ui-tools: ## Install tmux and Chromium (Debian's), which the tests drive lbctl top and the bench's report with, when missing
	@command -v tmux >/dev/null && command -v chromium >/dev/null || { sudo=; [ "$$(id -u)" = 0 ] || sudo=sudo; \
		$$sudo apt-get update -qq && \
		$$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq tmux chromium; }

# The comparisons of the kept fixtures with the shared set need it beside the repository (as CI
# lays it out); a clone alone skips them by name, and says so.
SHARED_SKIP := $(if $(wildcard ../shared/fixtures),,--skip _when_it_is_beside_the_repository)

real-kube: kubectl ## Build the pinned real Kubernetes control plane the tests hold local-kube to, and the release one minor up its upgrade rehearsal moves to (cached outside the clone)
	bash local/realkube/build.sh
	bash local/realkube/build.sh --upgrade

# Test binaries run side by side: most of their time is spent waiting on the processes they start.
TEST_JOBS ?= 3
test: venv lint-venv kubectl ui-tools own-cache ## The whole suite, emulator tests included, TEST_JOBS (3) test binaries at a time (README's and CI's command)
	@$(if $(SHARED_SKIP),echo "no shared set beside the repository: the kept copies are not compared",:)
	CARGO=$(CARGO) $(PYTHON) tests/suite.py --jobs $(TEST_JOBS) --beside 'bash local/realkube/build.sh >/dev/null && bash local/realkube/build.sh --upgrade >/dev/null' -- --include-ignored $(SHARED_SKIP)
	$(CARGO) test --workspace --doc

test-unit: own-cache ## Tests that need nothing but cargo (what plain `cargo test` runs)
	$(CARGO) test --workspace

lint: own-cache ## rustfmt check and clippy with warnings as errors
	$(CARGO) fmt --all --check
	$(CARGO) clippy --workspace --all-targets -- -D warnings

fmt: ## Format the code
	$(CARGO) fmt --all

bench: ## Merge benchmark on the 1024-route fixture (targets: 5 ms in-process, 15 ms process)
	$(CARGO) bench -p sidecar --bench merge

# The sidecar runs inside the CARLA image and any participant image (Ubuntu 18.04+): linked
# by zig against glibc 2.17, then checked for newer symbols.
SIDECAR_TARGET := x86_64-unknown-linux-gnu
SIDECAR_GLIBC := 2.17
SIDECAR_BIN := $(or $(CARGO_TARGET_DIR),target)/$(SIDECAR_TARGET)/release/lb-sidecar
SIDECAR_TOOLS := $(VENV)/.sidecar-tools

$(SIDECAR_TOOLS): sidecar/build-requirements.txt
	test -x $(VENV)/bin/pip || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check -r sidecar/build-requirements.txt
	touch $@

sidecar: $(SIDECAR_TOOLS) ## lb-sidecar for the Job images (glibc 2.17, checked)
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(CARGO) zigbuild --release -p sidecar --bin lb-sidecar --target $(SIDECAR_TARGET).$(SIDECAR_GLIBC)
	sidecar/check-glibc.sh $(SIDECAR_BIN) $(SIDECAR_GLIBC)

# Local runs in real time (time scale 1), 40 routes of 5 s on 4 pairs.
LATENCY_RUN := local run --time-scale 1 --routes 40 --workers 4 --route-seconds 5 --latency --timeout 900
bench-latency: venv kubectl own-cache ## Record -> partial update and last write -> final status, with and without S3's events (targets: p50 < 15 s, p99 < 60 s, final < 60 s)
	$(CARGO) build --quiet --workspace --bins
	@for run in "events, partial_update_seconds 20 (the default)|" \
	            "events, partial_update_seconds 30|--partial-update-seconds 30" \
	            "no events: safety net, holds and sweep only|--no-wake"; do \
		label=$${run%%|*}; flags=$${run#*|}; \
		line=$$($(TARGET_DIR)/debug/lbctl $(LATENCY_RUN) $$flags | grep '^latency') || exit 1; \
		printf '%-48s %s\n' "$$label" "$${line#latency        }"; \
	done

bench-scale: venv ui-tools ## The deadline rush. What AWS bills, on the node model (lb_domain::capacity::fleet): instance-hours, dollars, idle share by cause, evaluations and $/eval for the original's way, ours on-demand and ours Spot first, each lever, the start estimate's error, a long-run rush. Then 200 submissions of 40 teams through the shared EvalAI budget and the admission queue at 10x speed: EvalAI requests per sliding minute (target <= 60, no 429), arrival -> admitted and -> running, record -> partial update and end -> final delays; then its HTML report with plots, and a screenshot of it
	$(CARGO) bench -p lb-domain --bench fleet -- --bench
	$(CARGO) test --quiet -p e2e --bench scale -- --bench
	@bash tests/e2e/tools/headless.sh --window-size=1240,2200 --screenshot=$(abspath $(TARGET_DIR))/tmp/bench-scale/report.png $(TARGET_DIR)/tmp/bench-scale/report.html 2>/dev/null

bench-sidecar: venv ## logcopy's peak memory uploading a 1 GiB tree to moto (target < 20 MiB)
	$(CARGO) bench -p sidecar --bench logcopy

# Lambdas: cargo lambda (and its zig) from PyPI into .venv; x86-64 against an old glibc (arm64: LAMBDA_ARCH=arm64).
LAMBDA_ARCH ?= x86-64
LAMBDA_TOOLS := $(VENV)/.lambda-tools
FUNCTIONS := intake launch monitor finalize wake sweep
TARGET_DIR := $(or $(CARGO_TARGET_DIR),target)

# The target cache outside the clone serves every clone on the machine, and cargo knows a
# workspace crate by its path inside the workspace and by file times, not by clone: after a
# build in another clone, an older clone's crates pass as built, holding that clone's paths
# (`env!("CARGO_MANIFEST_DIR")`, from which the tests run cargo) and files (`include_str!`).
# A clone taking the cache over makes its own files newer than anything built from another.
.PHONY: own-cache
own-cache:
	@mkdir -p $(TARGET_DIR); stamp=$(TARGET_DIR)/.clone; \
	if [ "$$(cat $$stamp 2>/dev/null)" != "$(CURDIR)" ]; then \
		{ git ls-files -z 2>/dev/null || true; } | xargs -0 -r touch -c; \
		echo "$(CURDIR)" > $$stamp; \
	fi

$(LAMBDA_TOOLS): functions/build-requirements.txt
	test -x $(VENV)/bin/pip || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check -r functions/build-requirements.txt
	touch $@

build: $(LAMBDA_TOOLS) own-cache ## Lambda bootstraps (cargo lambda build --release) into $(TARGET_DIR)/lambda/<fn>/
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(CARGO) lambda build --release --$(LAMBDA_ARCH) $(addprefix -p ,$(FUNCTIONS))
	@for f in $(FUNCTIONS); do ls -l $(TARGET_DIR)/lambda/$$f/bootstrap; done

# Deployment (infra/README.md): SAM CLI and the AWS CLI, pinned, in a venv of their own (their
# pins would fight moto's in .venv). Nothing here runs in `make test`.
DEPLOY_VENV := .venv-deploy
DEPLOY_TOOLS := $(DEPLOY_VENV)/.installed
LEADERBOARD ?= 20
CLUSTER_STACK ?= leaderboard-$(LEADERBOARD)-cluster
AWS_CLI = $(DEPLOY_VENV)/bin/aws

$(DEPLOY_TOOLS): infra/requirements.txt
	$(PYTHON) -m venv $(DEPLOY_VENV)
	$(DEPLOY_VENV)/bin/pip install --quiet --disable-pip-version-check -r infra/requirements.txt
	touch $@

deploy: build $(DEPLOY_TOOLS) ## Build the bootstraps and deploy infra/app.yaml (AWS credentials; PARAMS="K=V ..." overrides)
	rm -rf infra/.build
	for f in $(FUNCTIONS); do mkdir -p infra/.build/$$f && cp $(TARGET_DIR)/lambda/$$f/bootstrap infra/.build/$$f/; done
	cd infra && SAM_CLI_TELEMETRY=0 ../$(DEPLOY_VENV)/bin/sam deploy --config-file samconfig.toml \
		--parameter-overrides Architecture=$(if $(filter arm64,$(LAMBDA_ARCH)),arm64,x86_64) $(PARAMS)

# One function's code, nothing else: cargo lambda deploy to the function the stack created (its
# name from the stack's outputs), which changes no setting the template owns, publishes a
# version and moves the function's `live` alias to it; then, for a function the state machine
# invokes, `lbctl ship` publishes a state machine version naming it and moves that alias too.
# BOOTSTRAP=<file> ships that binary instead of building one (the offline test uses it).
STACK ?= leaderboard
ALIAS := live
SM_FUNCTIONS := intake launch monitor finalize
FN_OUTPUT = $(shell printf '%s' '$(FN)' | sed 's/^./\U&/')FunctionName
FN_BOOTSTRAP = $(or $(BOOTSTRAP),$(TARGET_DIR)/lambda/$(FN)/bootstrap)
FN_ARCH = $(if $(filter arm64,$(LAMBDA_ARCH)),arm64,x86_64)
STACK_OUTPUT = $(AWS_CLI) cloudformation describe-stacks --stack-name $(STACK) \
	--query "Stacks[0].Outputs[?OutputKey=='$(1)'].OutputValue" --output text
# LBCTL=<file>: that lbctl instead of one built here (the offline test's, built with the others).
LBCTL ?=
LBCTL_BIN = $(or $(LBCTL),$(TARGET_DIR)/debug/lbctl)
BUILD_LBCTL = $(if $(LBCTL),:,$(CARGO) build --quiet -p cli --bin lbctl)
deploy-function: $(LAMBDA_TOOLS) $(DEPLOY_TOOLS) own-cache ## Ship FN=<name>'s new code to STACK's function as a new version, and the state machine version that runs it (code only; template changes: make deploy)
	@case " $(FUNCTIONS) " in *" $(FN) "*) ;; *) echo "FN must be one of: $(FUNCTIONS)" >&2; exit 2;; esac
	$(if $(BOOTSTRAP),,PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(CARGO) lambda build --release --$(LAMBDA_ARCH) -p $(FN))
	$(BUILD_LBCTL)
	@name=$$($(call STACK_OUTPUT,$(FN_OUTPUT))) || exit 1; \
	if [ -z "$$name" ] || [ "$$name" = None ]; then \
		echo "stack $(STACK) has no output $(FN_OUTPUT): run make deploy first" >&2; exit 1; fi; \
	arch=$$($(AWS_CLI) lambda get-function-configuration --function-name "$$name" \
		--query 'Architectures[0]' --output text) || exit 1; \
	if [ "$$arch" != "$(FN_ARCH)" ]; then \
		echo "$$name runs on $$arch but LAMBDA_ARCH=$(LAMBDA_ARCH) builds $(FN_ARCH)" >&2; exit 1; fi; \
	echo "$(FN) -> $$name"; \
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(CARGO) lambda deploy --binary-path $(FN_BOOTSTRAP) --alias $(ALIAS) "$$name" || exit 1; \
	version=$$($(AWS_CLI) lambda get-alias --function-name "$$name" --name $(ALIAS) \
		--query FunctionVersion --output text) || exit 1; \
	arn=$$($(AWS_CLI) lambda get-function-configuration --function-name "$$name" \
		--qualifier "$$version" --query FunctionArn --output text) || exit 1; \
	echo "$(FN): $(ALIAS) -> version $$version"; \
	case " $(SM_FUNCTIONS) " in *" $(FN) "*) \
		machine=$$($(call STACK_OUTPUT,StateMachineAliasArn)) || exit 1; \
		$(LBCTL_BIN) ship --state-machine "$$machine" --function-version "$$arn";; esac

# The state machine's alias back one version (TO=<n>: to that one); FN=<name>: that function's
# alias back one version instead (the wake, the sweep and the reaper's Finalize run through it).
rollback: $(DEPLOY_TOOLS) own-cache ## Point STACK's live alias back (state machine; FN=<name>: a function's): new submissions start there, runs in flight finish where they are
	@if [ -n "$(FN)" ]; then \
		case " $(FUNCTIONS) " in *" $(FN) "*) ;; *) echo "FN must be one of: $(FUNCTIONS)" >&2; exit 2;; esac; \
		name=$$($(call STACK_OUTPUT,$(FN_OUTPUT))) || exit 1; \
		now=$$($(AWS_CLI) lambda get-alias --function-name "$$name" --name $(ALIAS) \
			--query FunctionVersion --output text) || exit 1; \
		to=$${TO:-$$($(AWS_CLI) lambda list-versions-by-function --function-name "$$name" \
			--query 'Versions[].Version' --output text | tr '\t' '\n' | grep -E '^[0-9]+$$' \
			| awk -v now="$$now" '$$1 < now' | sort -n | tail -1)}; \
		if [ -z "$$to" ]; then echo "$$name: no version before $$now" >&2; exit 1; fi; \
		$(AWS_CLI) lambda update-alias --function-name "$$name" --name $(ALIAS) \
			--function-version "$$to" --query FunctionVersion --output text >/dev/null || exit 1; \
		echo "$$name: $(ALIAS) $$now -> $$to"; \
	else \
		$(BUILD_LBCTL); \
		machine=$$($(call STACK_OUTPUT,StateMachineAliasArn)) || exit 1; \
		$(LBCTL_BIN) rollback --state-machine "$$machine" $(if $(TO),--to $(TO)); \
	fi

cluster: $(DEPLOY_TOOLS) ## Deploy infra/cluster.yaml for LEADERBOARD=10|20 (PARAMS="K=V ..." overrides)
	$(AWS_CLI) cloudformation deploy --template-file infra/cluster.yaml --stack-name $(CLUSTER_STACK) \
		--capabilities CAPABILITY_IAM --no-fail-on-empty-changeset \
		--parameter-overrides ClusterName=leaderboard-$(LEADERBOARD) Bucket=leaderboard-$(LEADERBOARD)-results $(PARAMS)

cluster-manifests: $(DEPLOY_TOOLS) ## Apply infra/k8s/ to LEADERBOARD's cluster (kubeconfig via the AWS CLI)
	$(AWS_CLI) eks update-kubeconfig --name leaderboard-$(LEADERBOARD)
	role=$$($(AWS_CLI) cloudformation describe-stacks --stack-name $(CLUSTER_STACK) \
		--query "Stacks[0].Outputs[?OutputKey=='AutoscalerRoleArn'].OutputValue" --output text); \
	for f in namespace rbac network-policy nvidia-device-plugin cluster-autoscaler scheduler; do \
		sed -e "s|\$${CLUSTER_NAME}|leaderboard-$(LEADERBOARD)|g" -e "s|\$${AUTOSCALER_ROLE_ARN}|$$role|g" \
			infra/k8s/$$f.yaml | kubectl apply -f -; done

rehearse-upgrade: venv real-kube own-cache ## The Kubernetes upgrade with an evaluation in flight, on the real control plane: the control plane one minor up, then the GPU node group replaced (docs/operations.md)
	$(CARGO) build --quiet --workspace --bins
	$(TARGET_DIR)/debug/lbctl local run --kube real --scenario upgrade $(ARGS)

kubernetes-support: own-cache ## Where the clusters' Kubernetes minor stands in EKS's standard support (exit 1 within 60 days of its end)
	$(CARGO) run --quiet -p cli --bin lbctl -- kubernetes-support

local: venv kubectl own-cache ## One whole submission on this machine (ARGS="--scenario crash" etc.)
	$(CARGO) build --quiet --workspace --bins
	$(TARGET_DIR)/debug/lbctl local run $(ARGS)

# The harness only starts processes and servers: its own profile does not matter, so it is
# not rebuilt with LTO; the functions measured are the release bootstraps from `make build`.
bench-functions: build ## Cold start + one invocation of each Lambda as a process, with peak memory
	$(CARGO) test --quiet -p e2e --bench cold_start -- --bench

bench-stack: venv ## Start-up of moto + fake EvalAI + local Kubernetes API (target < 5 s)
	$(CARGO) test --quiet -p local-stack --bench startup -- --bench

clean: ## Remove build output and the venvs
	$(CARGO) clean
	rm -rf $(VENV) $(LINT_VENV)
