//! `lbctl <group> ...` for command groups that live in their own executable, `lbctl-<group>`,
//! found beside lbctl or on PATH (as git and cargo find theirs): the rehearsal (`lbctl local`)
//! is built from `local/` and never linked into the shipped tool.

use std::ffi::OsString;
use std::os::unix::process::CommandExt;
use std::path::PathBuf;
use std::process::Command;

use crate::{CliError, LogFormat};

/// Where `lbctl-<group>` is: beside this executable first (one build's binaries go together),
/// then on PATH.
pub fn locate(group: &str) -> Option<PathBuf> {
    let beside = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent().map(PathBuf::from));
    let on_path: Vec<PathBuf> = std::env::var_os("PATH")
        .map(|path| std::env::split_paths(&path).collect())
        .unwrap_or_default();
    first_in(beside.into_iter().chain(on_path), &format!("lbctl-{group}"))
}

/// The first of `dirs` holding a file `name`.
fn first_in(dirs: impl IntoIterator<Item = PathBuf>, name: &str) -> Option<PathBuf> {
    dirs.into_iter()
        .map(|dir| dir.join(name))
        .find(|p| p.is_file())
}

/// Replaces this process with `lbctl-<group> [-v...] <args>`; returns only on failure. The
/// log format travels in `LB_LOG_FORMAT`, which both read.
pub fn exec(group: &str, args: &[OsString], format: LogFormat, verbose: u8) -> CliError {
    let Some(program) = locate(group) else {
        return CliError::NotFound(format!(
            "`lbctl {group}` runs `lbctl-{group}`, which is neither beside lbctl nor on PATH \
             (`make local` builds it; or `cargo build -p local-cli`)"
        ));
    };
    let mut command = Command::new(&program);
    let format = match format {
        LogFormat::Text => "text",
        LogFormat::Json => "json",
    };
    command
        .env("LB_LOG_FORMAT", format)
        .args((0..verbose).map(|_| "-v"))
        .args(args);
    let error = command.exec();
    CliError::Refused(format!("cannot run `{}`: {error}", program.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_folder_holding_the_group_wins_and_a_folder_of_that_name_does_not_count() {
        let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        std::fs::create_dir(a.path().join("lbctl-local")).unwrap();
        std::fs::write(b.path().join("lbctl-local"), "").unwrap();
        let dirs = || [a.path().to_owned(), b.path().to_owned()];
        assert_eq!(
            first_in(dirs(), "lbctl-local"),
            Some(b.path().join("lbctl-local"))
        );
        assert_eq!(first_in(dirs(), "lbctl-other"), None);
    }
}
