//! `lb-sidecar merge`: workers' files on disk in, merged and EvalAI files out, all or nothing.

use std::fs;
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};

use lb_domain::results::{
    self, read_worker_file, EvalAiFiles, MergeOptions, MergeOutcome, ResultsError, ResultsFile,
    WorkerFile, MAX_FILE_BYTES,
};
use tracing::{info, warn};

use crate::cli::MergeArgs;

/// The files `merge` writes, relative to its output directory.
pub const OUTPUTS: [&str; 4] =
    ["agent_results.json", "evalai/results.json", "evalai/stdout.txt", "evalai/metadata.json"];

/// Why `merge` failed.
#[derive(Debug, thiserror::Error)]
pub enum MergeError {
    /// The results themselves are bad.
    #[error(transparent)]
    Results(#[from] ResultsError),
    /// `--subsets` does not give one subset per file.
    #[error("--subsets gives {subsets} subsets for {files} files")]
    SubsetCount {
        /// Subsets given.
        subsets: usize,
        /// Files given.
        files: usize,
    },
    /// A file exists but cannot be read.
    #[error("cannot read `{path}`: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// The outputs cannot be written.
    #[error("cannot write `{path}`: {source}")]
    Write {
        /// The file or directory.
        path: PathBuf,
        /// Why.
        #[source]
        source: io::Error,
    },
}

impl MergeError {
    /// Stable name for scripts and logs.
    pub fn name(&self) -> &'static str {
        match self {
            MergeError::Results(e) => e.name(),
            MergeError::SubsetCount { .. } => "InvalidArguments",
            MergeError::Read { .. } => "ReadFailed",
            MergeError::Write { .. } => "WriteFailed",
        }
    }
}

/// Runs the subcommand.
pub fn run(args: &MergeArgs) -> Result<(), MergeError> {
    let result = merge_files(args).and_then(|(outcome, files)| {
        write_outputs(&args.out, &outcome, args.leaderboard)?;
        Ok((outcome, files))
    });
    match result {
        Ok((outcome, files)) => {
            let m = &outcome.merged;
            if let Some(reason) = m.invalid_reason {
                // The official merge prints this too; operators re-scoring by hand look for it.
                println!("The statistics are badly formed. Setting their status to 'Invalid': {reason}");
            }
            println!(
                "merged {} records from {} of {} files: {}, entry status {}, progress {}/{}",
                m.records.len(),
                files,
                args.files.len(),
                if outcome.complete { "complete" } else { "partial" },
                m.entry_status,
                m.progress.0,
                m.progress.1
            );
            Ok(())
        }
        Err(err) => {
            // Never leave an older result behind to be mistaken for this one.
            remove_outputs(&args.out);
            Err(err)
        }
    }
}

/// Reads and merges the files; returns the outcome and how many files contributed.
pub fn merge_files(args: &MergeArgs) -> Result<(MergeOutcome, usize), MergeError> {
    if !args.subsets.is_empty() && args.subsets.len() != args.files.len() {
        return Err(MergeError::SubsetCount { subsets: args.subsets.len(), files: args.files.len() });
    }
    let mut present: Vec<ResultsFile> = Vec::with_capacity(args.files.len());
    for (i, path) in args.files.iter().enumerate() {
        let name = path.display().to_string();
        let bytes = read_limited(path)?;
        match read_worker_file(&name, bytes.as_deref(), args.leaderboard, args.subsets.get(i).copied())? {
            WorkerFile::Present(file) => present.push(file),
            WorkerFile::Empty(reason) => warn!(file = %name, %reason, "results file counts as empty"),
        }
    }
    let opts = MergeOptions {
        leaderboard: args.leaderboard,
        expected_records: args.expect_routes.map(|n| n.saturating_mul(args.repetitions)),
    };
    let outcome = results::merge(&present, opts)?;
    info!(
        records = outcome.merged.records.len(),
        complete = outcome.complete,
        entry_status = %outcome.merged.entry_status,
        "results merged"
    );
    Ok((outcome, present.len()))
}

/// The file's bytes, `None` if it does not exist; never reads more than the limit allows.
fn read_limited(path: &Path) -> Result<Option<Vec<u8>>, MergeError> {
    let read_err = |source| MergeError::Read { path: path.to_owned(), source };
    let file = match fs::File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(read_err(e)),
    };
    let mut bytes = Vec::new();
    // One byte over the limit is enough for the parser to report the file as too large.
    file.take(MAX_FILE_BYTES as u64 + 1).read_to_end(&mut bytes).map_err(read_err)?;
    Ok(Some(bytes))
}

/// Writes every output into a private directory first, then moves each into place.
fn write_outputs(
    out: &Path,
    outcome: &MergeOutcome,
    leaderboard: results::Leaderboard,
) -> Result<(), MergeError> {
    let write_err = |path: &Path| {
        let path = path.to_owned();
        move |source| MergeError::Write { path, source }
    };
    fs::create_dir_all(out.join("evalai")).map_err(write_err(out))?;
    let staging = tempfile::Builder::new()
        .prefix(".lb-merge-")
        .tempdir_in(out)
        .map_err(write_err(out))?;
    fs::create_dir(staging.path().join("evalai")).map_err(write_err(staging.path()))?;

    let evalai = EvalAiFiles::generate(Some(&outcome.merged), leaderboard);
    let contents: [(&str, String); 4] = [
        (OUTPUTS[0], outcome.merged.to_json()),
        (OUTPUTS[1], evalai.results_json()),
        (OUTPUTS[2], evalai.stdout.clone()),
        (OUTPUTS[3], evalai.metadata.clone().unwrap_or_default()),
    ];
    for (rel, text) in &contents {
        let path = staging.path().join(rel);
        let mut f = fs::File::create(&path).map_err(write_err(&path))?;
        f.write_all(text.as_bytes()).map_err(write_err(&path))?;
        f.sync_all().map_err(write_err(&path))?;
    }
    for (rel, _) in &contents {
        let target = out.join(rel);
        fs::rename(staging.path().join(rel), &target).map_err(write_err(&target))?;
    }
    Ok(())
}

fn remove_outputs(out: &Path) {
    for rel in OUTPUTS {
        let path = out.join(rel);
        match fs::remove_file(&path) {
            Ok(()) => warn!(file = %path.display(), "removed an earlier output"),
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => warn!(file = %path.display(), error = %e, "cannot remove an earlier output"),
        }
    }
}
