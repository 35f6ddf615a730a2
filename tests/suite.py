#!/usr/bin/env python3
"""Builds every test binary of the workspace once, then runs them side by side.

`cargo test` runs its test binaries one after another, and a few of them (the local runs, the
infrastructure checks) spend most of their minutes waiting on other processes. This runs
`--jobs` binaries at a time, the longest first, each as cargo would (from its package's
folder, with cargo's variables), prints each one's output whole as it ends, and exits
non-zero when any failed, naming them.

    tests/suite.py [--jobs N] [--timeout SECONDS] [--beside COMMAND] [-- ARGS FOR EVERY TEST BINARY]

`--beside` runs a command (another build some tests need) while cargo builds and the tests
run: on a new machine it overlaps both, and the tests that need what it builds wait for it
themselves (the real control plane's build.sh holds a lock while it builds). The run fails if
the command failed.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed

# Binaries that take minutes, started first so the short ones fill the other lanes.
LONG_FIRST = ["local-cli", "e2e", "sidecar", "lb-aws", "cli", "local-stack"]


def build(cargo):
    """The test executables of the workspace: (package, its folder, target source, path)."""
    out = subprocess.run(
        [cargo, "test", "--workspace", "--all-targets", "--no-run",
         "--message-format=json-render-diagnostics"],
        stdout=subprocess.PIPE, check=False, text=True)
    if out.returncode != 0:
        sys.exit(f"suite: the build failed (exit {out.returncode})")
    found = []
    for line in out.stdout.splitlines():
        msg = json.loads(line)
        if msg.get("reason") != "compiler-artifact" or not msg.get("executable"):
            continue
        if not msg["profile"]["test"] and "bench" not in msg["target"]["kind"]:
            continue
        package = msg["package_id"]
        manifest = msg["manifest_path"]
        name = package_name(package, manifest)
        found.append((name, os.path.dirname(manifest), msg["target"]["src_path"], msg["executable"]))
    # The binaries the tests start (lbctl, the sidecar, the fakes, the functions), built now as
    # the tests would build them (`cargo build --workspace --bins`), not by the first test to
    # ask while the others wait on cargo's lock.
    if subprocess.run([cargo, "build", "--quiet", "--workspace", "--bins"], check=False).returncode:
        sys.exit("suite: the build of the workspace's binaries failed")
    return found


def package_name(package_id, manifest):
    """`path+file:///…/local/cli#local-cli@0.1.0` and the older `local-cli 0.1.0 (path+…)`."""
    if "#" in package_id:
        tail = package_id.rsplit("#", 1)[1]
        return tail.split("@", 1)[0] if "@" in tail else os.path.basename(os.path.dirname(manifest))
    return package_id.split(" ", 1)[0]


def run(binary, args, timeout, cargo):
    name, folder, source, exe = binary
    env = dict(os.environ, CARGO=cargo, CARGO_MANIFEST_DIR=folder, CARGO_PKG_NAME=name)
    started = time.monotonic()
    with tempfile.TemporaryFile(mode="w+") as log:
        try:
            code = subprocess.run([exe, *args], cwd=folder, env=env, stdout=log,
                                  stderr=subprocess.STDOUT, timeout=timeout, check=False).returncode
        except subprocess.TimeoutExpired:
            code = None
        log.seek(0)
        output = log.read()
    return binary, code, output, time.monotonic() - started


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2, help="test binaries at a time (default 2)")
    parser.add_argument("--timeout", type=int, default=2400,
                        help="seconds one test binary may take before it is killed (default 2400)")
    parser.add_argument("--beside",
                        help="a shell command run while cargo builds and the tests run; it must succeed")
    parser.add_argument("args", nargs="*", help="passed to every test binary (after --)")
    opts = parser.parse_args()
    cargo = os.environ.get("CARGO", "cargo")
    beside = subprocess.Popen(opts.beside, shell=True) if opts.beside else None
    try:
        binaries = build(cargo)
    except BaseException:
        if beside:
            beside.terminate()
            beside.wait()
        raise
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    binaries.sort(key=lambda b: rank.get(b[0], len(LONG_FIRST)))
    root = os.getcwd()
    failed = []
    with ThreadPoolExecutor(max_workers=opts.jobs) as pool:
        runs = [pool.submit(run, b, opts.args, opts.timeout, cargo) for b in binaries]
        for done in as_completed(runs):
            (name, _, source, exe), code, output, seconds = done.result()
            print(f"     Running {os.path.relpath(source, root)} ({exe}) [{name}, {seconds:.0f} s]")
            print(output, end="" if output.endswith("\n") or not output else "\n", flush=True)
            if code != 0:
                why = f"killed after {opts.timeout} s" if code is None else f"exit {code}"
                failed.append(f"{os.path.relpath(source, root)} ({name}): {why}")
    if beside:
        try:
            code = beside.wait(timeout=opts.timeout)
        except subprocess.TimeoutExpired:
            beside.terminate()
            code = f"still running after {opts.timeout} s"
        if code:
            failed.append(f"`{opts.beside}` (beside): exit {code}")
    if failed:
        sys.exit("suite: failed:\n  " + "\n  ".join(failed))


if __name__ == "__main__":
    main()
