//! The layout tells the architecture: what ships never depends on what only rehearses it, and
//! the docs stay true to the tree (every repository path they name exists, nothing points
//! outside the repository: a clone alone is enough).
//!
//! `crates/`, `functions/`, `sidecar/` and `cli/` (`lbctl`) ship; `local/` (the embedded Step
//! Functions executor, the local stack, the fake EvalAI, the local Kubernetes API, the fake
//! workloads, `lbctl local`) and `tests/` exist to run and check them on one machine and may
//! appear in their `[dev-dependencies]` only.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use lb_domain::results::{EntryStatus, Leaderboard, RouteKind, RouteStatus};
use lb_domain::submission::SubmissionStatus;
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

/// Each package's features as `cargo tree` resolves them for the whole workspace, with the
/// dev-dependencies (what `cargo test` builds) or without them (what `cargo build --bins`
/// builds): `name version` -> features.
fn resolved_features(with_dev: bool) -> BTreeMap<String, String> {
    let mut args = vec!["tree", "--workspace", "--offline", "--prefix", "none"];
    args.extend(["--format", "{p}|{f}"]);
    if !with_dev {
        args.extend(["--edges", "no-dev"]);
    }
    let out = Command::new(env!("CARGO"))
        .args(args)
        .current_dir(root())
        .output()
        .expect("cargo tree runs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "cargo tree: {stderr}");
    features_of(&String::from_utf8_lossy(&out.stdout))
}

/// `cargo tree`'s `{p}|{f}` lines as `name version` -> features (a package's path and the
/// mark of one already shown dropped).
fn features_of(tree: &str) -> BTreeMap<String, String> {
    tree.lines()
        .map(|line| line.trim_end().trim_end_matches("(*)"))
        .filter_map(|line| line.split_once('|'))
        .map(|(package, features)| {
            let mut words = package.split_whitespace();
            let name: Vec<&str> = words.by_ref().take(2).collect();
            (name.join(" "), features.trim().to_string())
        })
        .collect()
}

/// The packages both builds hold whose features differ.
fn differing(bins: &BTreeMap<String, String>, tests: &BTreeMap<String, String>) -> Vec<String> {
    bins.iter()
        .filter_map(|(package, built)| {
            let tested = tests.get(package)?;
            (tested != built).then(|| format!("{package}: [{built}] shipped, [{tested}] tested"))
        })
        .collect()
}

/// A dev-dependency that turns on a feature of a shared dependency (a mocking crate's
/// `test-util`, serde_json's `preserve_order`) gives the tests a build of their own of it and
/// of everything above it: a new machine compiles most of the tree twice (the binaries that
/// `make local` and the tests run, then the tests), and the tests run code built otherwise than
/// what ships.
#[test]
fn the_tests_build_every_dependency_as_the_binaries_do() {
    let (bins, tests) = (resolved_features(false), resolved_features(true));
    assert!(bins.len() > 100, "only {} packages resolved", bins.len());
    let differ = differing(&bins, &tests);
    assert!(
        differ.is_empty(),
        "a dev-dependency changes what the binaries are built from:\n{}",
        differ.join("\n")
    );
}

#[test]
fn a_feature_only_the_tests_turn_on_is_found() {
    let bins = features_of("tokio v1.54.1|macros,rt\nlb-aws v0.1.0 (/w/crates/aws)|\n");
    let tests = features_of(
        "tokio v1.54.1|macros,rt,test-util (*)\nlb-aws v0.1.0 (/w/crates/aws)| (*)\nlb-aws v0.1.0 (/w/crates/aws)|\nproptest v1.0.0|std\n",
    );
    assert_eq!(bins.get("lb-aws v0.1.0").map(String::as_str), Some(""));
    assert_eq!(
        differing(&bins, &tests),
        ["tokio v1.54.1: [macros,rt] shipped, [macros,rt,test-util] tested"]
    );
    assert!(differing(&tests, &tests).is_empty());
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

/// `functions/{intake,wake}` -> `functions/intake`, `functions/wake`.
fn expand(path: &str) -> Vec<String> {
    match (path.find('{'), path.find('}')) {
        (Some(open), Some(close)) if open < close => path[open + 1..close]
            .split(',')
            .map(|alt| format!("{}{alt}{}", &path[..open], &path[close + 1..]))
            .collect(),
        _ => vec![path.to_owned()],
    }
}

/// This file, whose examples of what is not a path are not docs.
const SELF: &str = "tests/e2e/tests/layout.rs";

/// Folders whose files are not ours to check: build output, installs, recorded data.
const SKIPPED: &[&str] = &["target", ".git", ".venv", ".venv-deploy", "tests/fixtures"];

/// The top-level entries a repository path starts with.
const TOP: &[&str] = &[
    "crates/",
    "functions/",
    "local/",
    "tests/",
    "docs/",
    "infra/",
    "templates/",
    "statemachine/",
    "sidecar/",
    "cli/",
    ".ci/",
];

/// Every file under the repository with one of `extensions`, as (absolute, relative) paths.
fn files(extensions: &[&str]) -> Vec<(PathBuf, String)> {
    let root = root().canonicalize().unwrap();
    let mut out = Vec::new();
    let mut dirs = vec![root.clone()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            let rel = path
                .strip_prefix(&root)
                .unwrap()
                .to_string_lossy()
                .into_owned();
            if SKIPPED.contains(&rel.as_str()) {
                continue;
            }
            if rel == SELF {
                continue;
            }
            if path.is_dir() {
                dirs.push(path);
            } else if extensions.iter().any(|e| rel.ends_with(&format!(".{e}"))) {
                out.push((path, rel));
            }
        }
    }
    out.sort();
    out
}

/// The text a reader of `rel` sees as documentation: a Markdown file whole, a Rust file's
/// comments only.
fn documentation(path: &Path, rel: &str) -> String {
    let text = std::fs::read_to_string(path).unwrap();
    if rel.ends_with(".md") {
        return text;
    }
    text.lines()
        .filter_map(|l| l.trim_start().strip_prefix("//"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The repository paths named inside backticks in `text`, each with where it may be: from the
/// repository root or, as a package's README says `tests/x.rs`, from the file's package folder
/// (`package`); `../x` from the file's own folder. Placeholders, globs and commands run inside
/// a container (`./CarlaUE4.sh`) are not paths.
fn named_paths(text: &str, folder: &Path, package: &Path) -> Vec<(String, Vec<PathBuf>)> {
    let mut out = Vec::new();
    for span in text.split('`').skip(1).step_by(2) {
        for token in span.split_whitespace() {
            let token = token.trim_end_matches([',', ';', ':', ')', '.']);
            let token = token.split(['#', ':']).next().unwrap_or_default();
            if token.contains(['<', '*', '$', '=', '|']) {
                continue;
            }
            for path in expand(token) {
                let places = if path.starts_with("../") {
                    vec![folder.join(&path)]
                } else if TOP.iter().any(|t| path.starts_with(t)) {
                    vec![root().join(&path), package.join(&path)]
                } else {
                    continue;
                };
                out.push((path, places));
            }
        }
    }
    out
}

/// The folder of the package `path` belongs to (the nearest with a `Cargo.toml`), else the
/// repository root.
fn package_of(path: &Path) -> PathBuf {
    path.ancestors()
        .skip(1)
        .find(|dir| dir.join("Cargo.toml").is_file())
        .map_or_else(root, Path::to_owned)
}

#[test]
fn every_repository_path_the_docs_name_exists() {
    let mut missing = Vec::new();
    let mut checked = 0;
    for (path, rel) in files(&["md", "rs"]) {
        let (folder, package) = (path.parent().unwrap(), package_of(&path));
        for (named, places) in named_paths(&documentation(&path, &rel), folder, &package) {
            checked += 1;
            if !places.iter().any(|p| p.exists()) {
                missing.push(format!("{rel} names `{named}`, which does not exist"));
            }
        }
    }
    assert!(
        checked > 200,
        "only {checked} paths found: is the scan broken?"
    );
    assert!(missing.is_empty(), "{}", missing.join("\n"));
}

#[test]
fn nothing_points_outside_the_repository() {
    // The one exception: the test that keeps the repository's copy of the shared results
    // fixtures byte-identical to them when they lie beside the repository.
    let allowed = "crates/domain/tests/fixtures.rs";
    let outside = [
        "../shared",
        "shared/reference",
        "shared/fixtures",
        "DESIGN.md",
    ];
    let mut found = Vec::new();
    for (path, rel) in files(&["md", "rs", "toml", "yaml", "json", "sh"]) {
        if rel == allowed {
            continue;
        }
        let Ok(text) = std::fs::read_to_string(&path) else {
            continue;
        };
        for (n, line) in text.lines().enumerate() {
            if let Some(word) = outside.iter().find(|w| line.contains(**w)) {
                found.push(format!("{rel}:{}: `{word}`", n + 1));
            }
        }
    }
    // And the Makefile line that skips those comparisons by name where the set is absent.
    for (path, rel) in [
        (root().join("Makefile"), "Makefile"),
        (root().join(".ci/run"), ".ci/run"),
    ] {
        let text = std::fs::read_to_string(path).unwrap();
        let pointing = text
            .lines()
            .filter(|l| l.contains("../shared") && !l.starts_with("SHARED_SKIP :="));
        found.extend(pointing.map(|l| format!("{rel}: `{l}`")));
    }
    assert!(found.is_empty(), "{}", found.join("\n"));
}

#[test]
fn the_readme_stays_a_newcomers_page() {
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    assert!(
        readme.len() <= 8 * 1024,
        "README.md is {} bytes",
        readme.len()
    );
    for command in ["make local", "make test"] {
        assert!(readme.contains(command), "README.md lacks `{command}`");
    }
}

#[test]
fn a_placeholder_or_a_glob_is_not_a_path_and_a_relative_path_resolves_from_its_file() {
    let (folder, package) = (root().join("infra"), root().join("sidecar"));
    let named: Vec<String> = named_paths(
        "see `../cli/README.md`, `functions/{intake,wake}`, `functions/*/tests`, \
         `s3://<bucket>/x`, `app.yaml`, `./CarlaUE4.sh`, `tests/init.rs` and \
         `docs/storage.md#tables`",
        &folder,
        &package,
    )
    .into_iter()
    .map(|(named, places)| {
        assert!(places.iter().any(|p| p.exists()), "{named}");
        named
    })
    .collect();
    assert_eq!(
        named,
        [
            "../cli/README.md",
            "functions/intake",
            "functions/wake",
            "tests/init.rs",
            "docs/storage.md"
        ]
    );
    assert_eq!(
        package_of(&root().join("sidecar/src/main.rs")),
        root().join("sidecar")
    );
}

/// The longest a function may be, the rehearsal's included: a reader takes in one screen.
const MAX_FUNCTION_LINES: usize = 80;

/// The functions of a Rust source (outside its `#[cfg(test)]` module) longer than `max`
/// lines, as (name, lines): a rustfmt-formatted item ends at the first `}` back at the
/// indentation its `fn` line starts at.
fn long_functions(source: &str, max: usize) -> Vec<(String, usize)> {
    let lines: Vec<&str> = source.lines().collect();
    let mut long = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i];
        if line.trim_start().starts_with("#[cfg(test)]") {
            break;
        }
        let body = line.trim_start();
        let indent = line.len() - body.len();
        let head = ["pub(crate) ", "pub ", "async ", "const ", "unsafe "]
            .iter()
            .fold(body, |b, p| b.strip_prefix(p).unwrap_or(b));
        let head = head.strip_prefix("async ").unwrap_or(head);
        let Some(name) = head.strip_prefix("fn ") else {
            i += 1;
            continue;
        };
        let name: String = name
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        // A signature without a body (a trait's) ends in `;`.
        let Some(open) = (i..lines.len()).find(|&k| {
            let t = lines[k].trim_end();
            t.ends_with('{') || t.ends_with(';')
        }) else {
            break;
        };
        if lines[open].trim_end().ends_with(';') {
            i = open + 1;
            continue;
        }
        let close = (open + 1..lines.len())
            .find(|&k| {
                let l = lines[k];
                l.len() > indent && l[..indent].trim().is_empty() && l[indent..].starts_with('}')
            })
            .unwrap_or(lines.len() - 1);
        if close - i + 1 > max {
            long.push((name, close - i + 1));
        }
        i = close + 1;
    }
    long
}

/// Whether a source file is shipped code the screen rule covers.
fn shipped_source(rel: &str) -> bool {
    ["crates/", "functions/", "sidecar/", "cli/"]
        .iter()
        .any(|room| rel.starts_with(room))
        && rel.contains("/src/")
}

#[test]
fn no_function_is_longer_than_a_screen_the_rehearsals_included() {
    let mut long = Vec::new();
    for (path, rel) in files(&["rs"]) {
        if !(shipped_source(&rel) || rel.starts_with("local/") && rel.contains("/src/")) {
            continue;
        }
        let source = std::fs::read_to_string(path).unwrap();
        for (name, n) in long_functions(&source, MAX_FUNCTION_LINES) {
            long.push(format!("{rel}: {name} has {n} lines"));
        }
    }
    assert!(long.is_empty(), "split these:\n{}", long.join("\n"));
}

/// The words of the statuses, outcomes and leaderboards we keep as types (`lb_domain::status`,
/// `SubmissionStatus`, `Leaderboard`), from the types themselves: past parsing, none is
/// compared as a string.
fn typed_words() -> Vec<&'static str> {
    use lb_domain::status::{ExecutionStatus, PodPhase, Reaping, RecordStatus, Settled};
    let mut words: Vec<&'static str> = RecordStatus::ALL.iter().map(|s| s.as_str()).collect();
    words.extend(ExecutionStatus::ALL.iter().map(|s| s.as_str()));
    words.extend(SubmissionStatus::ALL.iter().map(|s| s.as_str()));
    words.extend(PodPhase::ALL.iter().map(|s| s.as_str()));
    // The results format's words: an entry's status, and those a route's status is exactly.
    // NB: `Invalid` is also a reason of Kubernetes' own `Status`, which is not ours to type.
    let entry = EntryStatus::ALL.iter().map(|s| s.as_str());
    words.extend(entry.filter(|w| !w.is_empty() && *w != "Invalid"));
    let route_words = ["Perfect", "Completed", "Started"];
    words.extend(
        route_words
            .into_iter()
            .filter(|w| RouteStatus::read(w.to_string()).kind() != RouteKind::Other),
    );
    words.extend([Settled::Unclaimed, Settled::Superseded].map(Settled::as_str));
    words.extend([Reaping::Left, Reaping::Released].map(Reaping::as_str));
    words.extend([Leaderboard::V1, Leaderboard::V2].map(Leaderboard::as_str));
    words
}

/// The lines of shipped code (outside `#[cfg(test)]`) that compare one of [`typed_words`] as a
/// string: `== "word"`, `"word" !=`, `matches!(x, "word" | ...)`. A `match` arm (`"word" =>`)
/// is parsing, and allowed.
fn string_comparisons(source: &str) -> Vec<String> {
    let words = typed_words();
    let mut found = Vec::new();
    // Parentheses still open in a `matches!(...)` that started on an earlier line.
    let mut open = 0i32;
    for line in source.lines() {
        if line.trim_start().starts_with("#[cfg(test)]") {
            break;
        }
        let code = line.split("//").next().unwrap_or_default();
        let matched = open > 0 || code.contains("matches!(");
        if matched {
            let from = if open > 0 {
                code
            } else {
                &code[code.find("matches!(").unwrap_or(0)..]
            };
            open += from.matches('(').count() as i32 - from.matches(')').count() as i32;
            open = open.max(0);
        }
        for word in &words {
            let quoted = format!("\"{word}\"");
            let compared = [
                format!("== {quoted}"),
                format!("!= {quoted}"),
                format!("{quoted} =="),
                format!("{quoted} !="),
            ]
            .iter()
            .any(|p| code.contains(p.as_str()));
            if compared || (matched && code.contains(&quoted) && !code.contains("=>")) {
                found.push(line.trim().to_owned());
                break;
            }
        }
    }
    found
}

#[test]
fn no_status_outcome_or_leaderboard_is_compared_as_a_string_outside_parsing() {
    let found: Vec<String> = files(&["rs"])
        .into_iter()
        .filter(|(_, rel)| shipped_source(rel))
        .flat_map(|(path, rel)| {
            let source = std::fs::read_to_string(path).unwrap();
            string_comparisons(&source)
                .into_iter()
                .map(move |line| format!("{rel}: {line}"))
        })
        .collect();
    assert!(
        found.is_empty(),
        "compare the parsed type, not its word:\n{}",
        found.join("\n")
    );
    // The rule finds what it is for, and leaves parsing alone.
    let example = "if s == \"FAILED\" {}\nlet x = matches!(s,\n    \"queued\" | \"running\");\nmatch s { \"2.0\" => V2 }\n#[cfg(test)]\nif s == \"left\" {}";
    assert_eq!(
        string_comparisons(example),
        ["if s == \"FAILED\" {}", "\"queued\" | \"running\");"]
    );
}

/// Each package links its integration tests once: one test target, `tests/main.rs`, whose
/// modules are the other files of `tests/` (each test binary links the whole dependency graph,
/// and there were 60 of them). A file `tests/main.rs` does not declare would never run.
#[test]
fn each_package_has_one_integration_test_binary_that_holds_every_test_file() {
    let meta = metadata();
    let root = root();
    let mut wrong = Vec::new();
    for package in meta["packages"].as_array().unwrap() {
        let manifest = package["manifest_path"].as_str().unwrap();
        let dir = Path::new(manifest).parent().unwrap();
        let name = folder(manifest, &root);
        let tests: Vec<&str> = package["targets"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|t| t["kind"][0] == "test")
            .map(|t| t["src_path"].as_str().unwrap())
            .collect();
        let files: Vec<String> = std::fs::read_dir(dir.join("tests"))
            .into_iter()
            .flatten()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|f| f.ends_with(".rs") && f != "main.rs")
            .collect();
        if tests.is_empty() && files.is_empty() {
            continue;
        }
        let main = dir.join("tests/main.rs");
        if tests.len() != 1 || Path::new(tests[0]) != main {
            wrong.push(format!("{name}: test targets {tests:?}, not tests/main.rs alone (set `autotests = false` and one [[test]])"));
            continue;
        }
        let declared = std::fs::read_to_string(&main).unwrap();
        for file in files {
            let module = format!("mod {};", file.trim_end_matches(".rs"));
            if !declared.lines().any(|l| l.trim() == module) {
                wrong.push(format!(
                    "{name}: tests/{file} is not a module of tests/main.rs, so it never runs"
                ));
            }
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// A crate's public modules, from its `lib.rs`.
fn public_modules(lib: &str) -> Vec<String> {
    lib.lines()
        .filter_map(|line| line.trim().strip_prefix("pub mod "))
        .map(|rest| rest.trim_end_matches(';').trim().to_owned())
        .collect()
}

#[test]
fn every_crate_readme_names_each_of_its_public_modules() {
    let mut missing = Vec::new();
    for entry in std::fs::read_dir(root().join("crates")).unwrap() {
        let dir = entry.unwrap().path();
        let lib = std::fs::read_to_string(dir.join("src/lib.rs")).unwrap();
        let readme = std::fs::read_to_string(dir.join("README.md")).unwrap_or_default();
        // A folder's modules are named too: the README is the map of the folders.
        let folders = public_modules(&lib).into_iter().flat_map(|module| {
            let inner = std::fs::read_to_string(dir.join("src").join(&module).join("mod.rs"));
            let inner = inner.map(|m| public_modules(&m)).unwrap_or_default();
            std::iter::once(module).chain(inner)
        });
        for module in folders.collect::<Vec<_>>() {
            if !readme.contains(&format!("`{module}`")) {
                missing.push(format!("{}: `{module}`", dir.display()));
            }
        }
    }
    assert!(
        missing.is_empty(),
        "READMEs that miss a module:\n{}",
        missing.join("\n")
    );
    assert_eq!(
        public_modules("//! x\npub mod a;\nmod b;\n    pub mod c;\n"),
        ["a", "c"]
    );
}

#[test]
fn every_decision_record_says_its_status_and_a_superseded_one_names_its_successor() {
    let dir = root().join("docs/adr");
    let mut problems = Vec::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        if name == "README.md" || !name.ends_with(".md") {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap();
        let Some(status) = text.lines().find_map(|l| l.strip_prefix("Status: ")) else {
            problems.push(format!("{name}: no `Status:` line"));
            continue;
        };
        if let Some(by) = status.strip_prefix("superseded by `") {
            let successor = by.split('`').next().unwrap_or_default();
            if !dir.join(successor).is_file() {
                problems.push(format!(
                    "{name}: superseded by a record that does not exist"
                ));
            }
        } else if !status.starts_with("accepted") {
            problems.push(format!(
                "{name}: status `{status}` is neither accepted nor superseded"
            ));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn a_long_function_is_found_and_a_test_module_is_not_counted() {
    let body = "    let x = 1;\n".repeat(80);
    let source = format!(
        "/// Short.\npub fn short() -> u8 {{\n    1\n}}\n\npub async fn long() {{\n{body}}}\n\ntrait T {{\n    fn sig(&self);\n}}\n\n#[cfg(test)]\nmod tests {{\n    fn huge() {{\n{body}{body}    }}\n}}\n"
    );
    assert_eq!(long_functions(&source, 80), [("long".to_string(), 82)]);
    assert!(long_functions(&source, 82).is_empty());
}

/// The domain's root modules and folders, lowest layer first: each may use its own and those
/// before it, never one after it, so the run's rules sit on the cluster's view, capacity and
/// the results, and nothing below knows a stage.
const DOMAIN_LAYERS: &[&str] = &[
    "errors",
    "status",
    "results",
    "submission",
    "job",
    "cluster",
    "capacity",
    "settings",
    "run",
];

/// The root modules of the domain a source names through `crate::` (code, doc links and
/// `error_names!`'s helpers alike).
fn domain_uses(source: &str) -> Vec<String> {
    let mut used: Vec<String> = source
        .split("crate::")
        .skip(1)
        .map(|rest| {
            rest.chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect::<String>()
        })
        .map(|name| match name.as_str() {
            "error_names" | "__transient" => "errors".to_owned(),
            _ => name,
        })
        .collect();
    used.sort();
    used.dedup();
    used
}

#[test]
fn the_domain_is_folders_in_layers_and_none_uses_a_higher_one() {
    let src = root().join("crates/domain/src");
    let lib = std::fs::read_to_string(src.join("lib.rs")).unwrap();
    let mut declared = public_modules(&lib);
    declared.retain(|m| m != "testutil");
    let mut layers = DOMAIN_LAYERS.to_vec();
    layers.sort();
    assert_eq!(
        declared, layers,
        "lib.rs's modules are the layers, each placed in DOMAIN_LAYERS"
    );
    let flat: Vec<String> = std::fs::read_dir(&src)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|f| f.ends_with(".rs"))
        .collect();
    assert!(
        flat.len() <= 6,
        "crates/domain/src holds {} flat files: {flat:?}",
        flat.len()
    );
    let mut wrong = Vec::new();
    for (level, layer) in DOMAIN_LAYERS.iter().enumerate() {
        let single = src.join(format!("{layer}.rs"));
        let sources: Vec<PathBuf> = if single.is_file() {
            vec![single]
        } else {
            // A layer's folder, with the folders of its larger modules (`capacity/fleet/`).
            let mut files = Vec::new();
            let mut dirs = vec![src.join(layer)];
            while let Some(dir) = dirs.pop() {
                for entry in std::fs::read_dir(&dir).unwrap() {
                    let path = entry.unwrap().path();
                    if path.is_dir() {
                        dirs.push(path);
                    } else {
                        files.push(path);
                    }
                }
            }
            files
        };
        for path in sources {
            let source = std::fs::read_to_string(&path).unwrap();
            for used in domain_uses(&source) {
                let above = DOMAIN_LAYERS
                    .iter()
                    .position(|l| *l == used)
                    .map(|p| p > level);
                if above.unwrap_or(false) {
                    wrong.push(format!("{}: uses `{used}`", path.display()));
                }
            }
        }
    }
    assert!(
        wrong.is_empty(),
        "a lower layer uses a higher one:\n{}",
        wrong.join("\n")
    );
    assert_eq!(
        domain_uses("use crate::run::x;\n/// [`crate::job::y`]\ncrate::error_names! {}"),
        ["errors", "job", "run"]
    );
}

/// A shipped crate's files as module paths (`run::round` for `src/run/round.rs`, `run` for
/// `src/run/mod.rs`), each with the source it holds outside its `#[cfg(test)]` module and
/// comments.
fn crate_modules(src: &Path) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut dirs = vec![src.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                dirs.push(path);
                continue;
            }
            let Some(rel) = path.strip_prefix(src).unwrap().to_str() else {
                continue;
            };
            let Some(rel) = rel.strip_suffix(".rs") else {
                continue;
            };
            let module = match rel {
                "lib" | "main" => String::new(),
                _ => rel.trim_end_matches("/mod").replace('/', "::"),
            };
            let text = std::fs::read_to_string(&path).unwrap();
            let code: Vec<&str> = text
                .lines()
                .take_while(|l| !l.trim_start().starts_with("#[cfg(test)]"))
                .filter(|l| !l.trim_start().starts_with("//"))
                .collect();
            out.push((module, code.join("\n")));
        }
    }
    out
}

/// The import edges between a crate's files: `a -> b` when `a` names `crate::b...` (the
/// longest module path that is a file) outside tests and comments.
fn import_edges(modules: &[(String, String)]) -> Vec<(String, String)> {
    let known: std::collections::BTreeSet<&str> = modules.iter().map(|(m, _)| m.as_str()).collect();
    let mut edges = Vec::new();
    for (module, code) in modules {
        for rest in code.split("crate::").skip(1) {
            let path: String = rest
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':')
                .collect();
            let mut target = path.trim_end_matches(':').to_owned();
            while !target.is_empty() && !known.contains(target.as_str()) {
                target = target
                    .rsplit_once("::")
                    .map(|(a, _)| a.to_owned())
                    .unwrap_or_default();
            }
            if !target.is_empty()
                && &target != module
                && !module.starts_with(&format!("{target}::"))
            {
                edges.push((module.clone(), target));
            }
        }
    }
    edges.sort();
    edges.dedup();
    edges
}

/// One import circle among the edges, as the modules around it, if there is one.
fn a_circle(edges: &[(String, String)]) -> Option<Vec<String>> {
    fn visit<'a>(
        node: &'a str,
        edges: &'a [(String, String)],
        path: &mut Vec<&'a str>,
        done: &mut std::collections::BTreeSet<&'a str>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|n| *n == node) {
            return Some(path[at..].iter().map(|s| s.to_string()).collect());
        }
        if !done.insert(node) {
            return None;
        }
        path.push(node);
        for (_, to) in edges.iter().filter(|(from, _)| from == node) {
            if let Some(circle) = visit(to, edges, path, done) {
                return Some(circle);
            }
        }
        path.pop();
        None
    }
    let mut done = std::collections::BTreeSet::new();
    edges
        .iter()
        .find_map(|(from, _)| visit(from, edges, &mut Vec::new(), &mut done))
}

#[test]
fn no_shipped_crate_has_an_import_circle_among_its_files() {
    let meta = metadata();
    let root = root();
    let mut circles = Vec::new();
    for package in meta["packages"].as_array().unwrap() {
        let manifest = package["manifest_path"].as_str().unwrap();
        let name = folder(manifest, &root);
        if !ships(&name) {
            continue;
        }
        let src = Path::new(manifest).parent().unwrap().join("src");
        if let Some(circle) = a_circle(&import_edges(&crate_modules(&src))) {
            circles.push(format!("{name}: {}", circle.join(" -> ")));
        }
    }
    assert!(
        circles.is_empty(),
        "import circles:\n{}",
        circles.join("\n")
    );
    // The rule finds a circle through a longer path, and a tree has none.
    let modules = [
        ("a".to_owned(), "use crate::b::c::Thing;".to_owned()),
        ("b::c".to_owned(), "use crate::d;".to_owned()),
        ("d".to_owned(), "crate::a::f()".to_owned()),
    ];
    assert_eq!(
        a_circle(&import_edges(&modules)).unwrap(),
        ["a", "b::c", "d"]
    );
    assert_eq!(a_circle(&import_edges(&modules[..2])), None);
}

/// The first paragraph of a source's `//!` header, on one line, without its final period.
fn header_summary(source: &str) -> String {
    let lines: Vec<&str> = source
        .lines()
        .map_while(|l| l.strip_prefix("//!"))
        .map(str::trim)
        .take_while(|l| !l.is_empty())
        .collect();
    lines.join(" ").trim_end_matches('.').to_owned()
}

#[test]
fn each_package_says_what_it_is_once_in_its_header_and_its_manifest_repeats_it() {
    let meta = metadata();
    let root = root();
    let mut drift = Vec::new();
    for package in meta["packages"].as_array().unwrap() {
        let manifest = package["manifest_path"].as_str().unwrap();
        let dir = Path::new(manifest).parent().unwrap();
        let lib = dir.join("src/lib.rs");
        let top = if lib.is_file() {
            lib
        } else {
            dir.join("src/main.rs")
        };
        let summary = header_summary(&std::fs::read_to_string(&top).unwrap());
        let description = package["description"].as_str().unwrap_or_default();
        if summary.is_empty() || description != summary {
            drift.push(format!(
                "{}: description `{description}`, header `{summary}`",
                folder(manifest, &root)
            ));
        }
    }
    assert!(
        drift.is_empty(),
        "say it once, in the header, and copy it:\n{}",
        drift.join("\n")
    );
    assert_eq!(
        header_summary("//! One\n//! two.\n//!\n//! Three.\nuse x;"),
        "One two"
    );
}

#[test]
fn every_module_opens_with_a_header_saying_what_it_holds() {
    let bare: Vec<String> = files(&["rs"])
        .into_iter()
        .filter(|(_, rel)| {
            (shipped_source(rel) || rel.starts_with("local/")) && rel.contains("/src/")
        })
        .filter(|(_, rel)| !rel.ends_with("/main.rs"))
        .filter(|(path, _)| header_summary(&std::fs::read_to_string(path).unwrap()).is_empty())
        .map(|(_, rel)| rel)
        .collect();
    assert!(
        bare.is_empty(),
        "modules without a `//!` header:\n{}",
        bare.join("\n")
    );
}

/// The lines of a source (outside `#[cfg(test)]`) that name one of the submission record's
/// attributes as a string, in a file that handles DynamoDB items (`AttributeValue`).
fn record_attribute_names(source: &str) -> Vec<String> {
    let code: Vec<&str> = source
        .lines()
        .take_while(|l| !l.trim_start().starts_with("#[cfg(test)]"))
        .collect();
    if !code.iter().any(|l| l.contains("AttributeValue")) {
        return Vec::new();
    }
    code.iter()
        .filter(|l| !l.trim_start().starts_with("//"))
        .filter(|l| {
            // NB: `"name": value` is a JSON object's key (a payload's), not an attribute.
            lb_aws::record::attr::LAYOUT.iter().any(|name| {
                let quoted = format!("\"{name}\"");
                l.match_indices(&quoted)
                    .any(|(at, _)| !l[at + quoted.len()..].starts_with(':'))
            })
        })
        .map(|l| l.trim().to_owned())
        .collect()
}

#[test]
fn only_lb_aws_names_the_submission_records_attributes() {
    let found: Vec<String> = files(&["rs"])
        .into_iter()
        .filter(|(_, rel)| {
            (shipped_source(rel) || rel.starts_with("local/") && rel.contains("/src/"))
                && !rel.starts_with("crates/aws/")
        })
        .flat_map(|(path, rel)| {
            let source = std::fs::read_to_string(path).unwrap();
            record_attribute_names(&source)
                .into_iter()
                .map(move |line| format!("{rel}: {line}"))
        })
        .collect();
    assert!(
        found.is_empty(),
        "read the record through lb_aws::record::StoredRecord:\n{}",
        found.join("\n")
    );
    let example = "use x::AttributeValue;\nlet s = item.get(\"gpu_seconds\");\n// \"cost_usd\"\n#[cfg(test)]\nlet t = item.get(\"error\");";
    assert_eq!(
        record_attribute_names(example),
        ["let s = item.get(\"gpu_seconds\");"]
    );
    assert!(record_attribute_names("let s = body[\"gpu_seconds\"];").is_empty());
    let payload = "use x::AttributeValue;\njson!({\"submission_id\": 7});";
    assert!(record_attribute_names(payload).is_empty());
}

/// The decisions a shell takes from `lb_domain` (outside `#[cfg(test)]`): a function imported
/// by name, or one called through a module it imports (`cost::judge(`) or by its whole path.
/// Types, constants and methods on types (parsing at the edge) are not decisions.
fn domain_decisions(source: &str) -> Vec<String> {
    let code: Vec<&str> = source
        .lines()
        .take_while(|l| !l.trim_start().starts_with("#[cfg(test)]"))
        .filter(|l| !l.trim_start().starts_with("//"))
        .collect();
    let code = code.join("\n");
    let lowercase = |s: &str| s.chars().next().is_some_and(|c| c.is_ascii_lowercase());
    let mut found = Vec::new();
    let mut modules = Vec::new();
    for import in code.split("use lb_domain::").skip(1) {
        let import = import.split(';').next().unwrap_or_default();
        let (path, items) = match import.split_once('{') {
            Some((path, items)) => (path.trim_end_matches("::"), items.trim_end_matches('}')),
            None => import.rsplit_once("::").unwrap_or(("", import)),
        };
        for item in items.split(',').map(str::trim).filter(|i| !i.is_empty()) {
            if item == "self" {
                modules.push(path.rsplit("::").next().unwrap_or(path).to_owned());
            } else if lowercase(item) {
                found.push(format!("imports `{path}::{item}`"));
            }
        }
    }
    let called = |prefix: &str| {
        code.split(prefix)
            .skip(1)
            .filter_map(|rest| {
                let name: String = rest
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                (lowercase(&name) && rest[name.len()..].starts_with('(')).then_some(name)
            })
            .collect::<Vec<_>>()
    };
    for module in modules {
        for name in called(&format!("{module}::")) {
            found.push(format!("calls `{module}::{name}`"));
        }
    }
    for rest in code.split("lb_domain::").skip(1) {
        let path: String = rest
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':')
            .collect();
        let last = path.rsplit("::").next().unwrap_or_default();
        if lowercase(last) && rest[path.len()..].starts_with('(') {
            found.push(format!("calls `lb_domain::{path}`"));
        }
    }
    found
}

#[test]
fn the_monitor_and_finalize_shells_perform_steps_and_take_no_decision_from_the_domain() {
    let mut found = Vec::new();
    for shell in [
        "functions/monitor/src/io.rs",
        "functions/finalize/src/io.rs",
    ] {
        let source = std::fs::read_to_string(root().join(shell)).unwrap();
        found.extend(
            domain_decisions(&source)
                .into_iter()
                .map(|d| format!("{shell}: {d}")),
        );
    }
    assert!(
        found.is_empty(),
        "the round or the closing decides; the shell only performs:\n{}",
        found.join("\n")
    );
    let example = "use lb_domain::capacity::cost::{self, Totals};\nuse lb_domain::job::logtail::participant_tail;\nfn f() { cost::judge(x); let _ = cost::LIMIT; lb_domain::cluster::disruption::leaving(None); Totals::default(); }";
    assert_eq!(
        domain_decisions(example),
        [
            "imports `job::logtail::participant_tail`",
            "calls `cost::judge`",
            "calls `lb_domain::cluster::disruption::leaving`"
        ]
    );
}

/// Where the ledger's compact form lives: the only shipped file that may spell base 36.
const LEDGER_CODE: &str = "crates/domain/src/capacity/ledger_code.rs";

#[test]
fn the_ledgers_compact_form_is_spelled_in_one_module() {
    let spelled = |source: &str| {
        source
            .lines()
            .take_while(|l| !l.trim_start().starts_with("#[cfg(test)]"))
            .filter(|l| !l.trim_start().starts_with("//"))
            .any(|l| {
                let l = l.replace(' ', "");
                ["_radix(", "_digit("].iter().any(|call| l.contains(call)) && l.contains(",36)")
                    || l.contains(".to_digit(36)")
            })
    };
    let found: Vec<String> = files(&["rs"])
        .into_iter()
        .filter(|(_, rel)| shipped_source(rel) && rel != LEDGER_CODE)
        .filter(|(path, _)| spelled(&std::fs::read_to_string(path).unwrap()))
        .map(|(_, rel)| rel)
        .collect();
    assert!(found.is_empty(), "base 36 outside {LEDGER_CODE}: {found:?}");
    let here = std::fs::read_to_string(root().join(LEDGER_CODE)).unwrap();
    assert!(
        spelled(&here),
        "the rule no longer finds the encoding it is for"
    );
    assert!(!spelled("let n = u64::from_str_radix(s, 16);"));
}

#[test]
fn the_rehearsal_imports_nothing_of_the_sidecar() {
    // NB: what both need is a crate of its own (`crates/proc`): the rehearsal stands in for
    // the cluster around the sidecar, never for the sidecar's own code.
    let meta = metadata();
    let root = root();
    let mut wrong = Vec::new();
    for package in meta["packages"].as_array().unwrap() {
        let manifest = package["manifest_path"].as_str().unwrap();
        let name = folder(manifest, &root);
        if !name.starts_with("local/") {
            continue;
        }
        for dep in package["dependencies"].as_array().unwrap() {
            if dep["name"] == "sidecar" {
                wrong.push(name.clone());
            }
        }
    }
    assert!(wrong.is_empty(), "these depend on the sidecar: {wrong:?}");
}
