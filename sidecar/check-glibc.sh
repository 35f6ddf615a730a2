#!/usr/bin/env bash
# Fails when BINARY needs a glibc symbol version newer than MAX, or a shared library that is
# not part of glibc: the sidecar must run in any glibc-based image (Ubuntu 18.04+, CARLA's).
set -euo pipefail
bin=${1:?usage: check-glibc.sh BINARY MAX_GLIBC}
max=${2:?usage: check-glibc.sh BINARY MAX_GLIBC}
newest=$(objdump -T "$bin" | grep -o 'GLIBC_[0-9][0-9.]*' | sed 's/GLIBC_//' | sort -uV | tail -n 1)
if [[ -z "$newest" ]]; then
    echo "$bin: no versioned glibc symbols (static?)"
elif [[ "$(printf '%s\n%s\n' "$newest" "$max" | sort -V | tail -n 1)" != "$max" ]]; then
    echo "$bin needs GLIBC_$newest, newer than $max:" >&2
    objdump -T "$bin" | grep "GLIBC_$newest" >&2
    exit 1
fi
libs=$(readelf -d "$bin" | sed -n 's/.*Shared library: \[\(.*\)\]/\1/p')
for lib in $libs; do
    case "$lib" in
        libc.so.6 | libm.so.6 | libpthread.so.0 | libdl.so.2 | librt.so.1 | ld-linux-x86-64.so.2) ;;
        *) echo "$bin needs $lib, which is not part of glibc" >&2; exit 1 ;;
    esac
done
echo "$bin: newest glibc symbol GLIBC_${newest:-none} <= $max; libraries: $(echo $libs)"
