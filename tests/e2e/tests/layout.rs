//! The layout tells the architecture: what ships never depends on what only rehearses it.
//!
//! `crates/`, `functions/`, `sidecar/` and `cli/` (`lbctl`) ship; `local/` (the embedded Step
//! Functions executor, the local stack, the fake EvalAI, the local Kubernetes API, the fake
//! workloads, `lbctl local`) and `tests/` exist to run and check them on one machine and may
//! appear in their `[dev-dependencies]` only.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn metadata() -> Value {
    let out = Command::new(env!("CARGO"))
        .args([
            "metadata",
            "--format-version",
            "1",
            "--no-deps",
            "--offline",
        ])
        .current_dir(root())
        .output()
        .expect("cargo metadata runs");
    assert!(
        out.status.success(),
        "cargo metadata: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("cargo metadata prints JSON")
}

/// The package's folder relative to the workspace root, e.g. `local/kube`.
fn folder(manifest_path: &str, root: &Path) -> String {
    let dir = Path::new(manifest_path).parent().unwrap();
    let root = root.canonicalize().unwrap();
    dir.canonicalize()
        .unwrap()
        .strip_prefix(&root)
        .unwrap()
        .to_string_lossy()
        .into_owned()
}

fn ships(folder: &str) -> bool {
    ["crates/", "functions/", "sidecar", "cli"]
        .iter()
        .any(|p| folder.starts_with(p))
}

#[test]
fn nothing_that_ships_depends_on_local_or_tests_outside_dev_dependencies() {
    let meta = metadata();
    let root = root();
    let packages = meta["packages"].as_array().unwrap();
    let mut shipped = 0;
    let mut violations = Vec::new();
    for package in packages {
        let here = folder(package["manifest_path"].as_str().unwrap(), &root);
        if !ships(&here) {
            continue;
        }
        shipped += 1;
        for dep in package["dependencies"].as_array().unwrap() {
            let Some(path) = dep["path"].as_str() else {
                continue;
            };
            let there = folder(&format!("{path}/Cargo.toml"), &root);
            let kind = dep["kind"].as_str().unwrap_or("normal");
            let rehearses = there.starts_with("local/") || there.starts_with("tests/");
            if rehearses && kind != "dev" {
                violations.push(format!(
                    "{here} has `{}` ({there}) as a {kind} dependency",
                    dep["name"].as_str().unwrap()
                ));
            }
        }
    }
    assert!(shipped >= 10, "found only {shipped} shipped packages");
    assert!(violations.is_empty(), "{}", violations.join("\n"));
}

#[test]
fn the_readme_layout_table_names_every_package_folder_and_only_folders_that_exist() {
    let root = root();
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let table: Vec<&str> = readme
        .split("## Layout")
        .nth(1)
        .expect("README has a Layout section")
        .lines()
        .skip_while(|l| !l.starts_with('|'))
        .take_while(|l| l.starts_with('|'))
        .collect();
    // Every `path` in the table's first column exists (`{a,b}` expanded).
    let mut named = Vec::new();
    for row in table.iter().skip(2) {
        let first = row.split('|').nth(1).unwrap_or_default();
        for quoted in first.split('`').skip(1).step_by(2) {
            named.extend(expand(quoted));
        }
    }
    let missing: Vec<_> = named
        .iter()
        .filter(|p| !root.join(p.trim_end_matches('/')).exists())
        .collect();
    assert!(
        missing.is_empty(),
        "README names missing paths: {missing:?}"
    );
    // Every workspace package's folder is in the table.
    let meta = metadata();
    for package in meta["packages"].as_array().unwrap() {
        let here = folder(package["manifest_path"].as_str().unwrap(), &root);
        assert!(
            named
                .iter()
                .any(|p| p.trim_end_matches('/') == here || here.starts_with(p.as_str())),
            "README's layout table does not name `{here}`"
        );
    }
}

/// `functions/{a,b}` -> `functions/a`, `functions/b`.
fn expand(path: &str) -> Vec<String> {
    match (path.find('{'), path.find('}')) {
        (Some(open), Some(close)) if open < close => path[open + 1..close]
            .split(',')
            .map(|alt| format!("{}{alt}{}", &path[..open], &path[close + 1..]))
            .collect(),
        _ => vec![path.to_owned()],
    }
}
