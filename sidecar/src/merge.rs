//! `lb-sidecar merge`: workers' files on disk in, merged and EvalAI files out, all or nothing.

use std::fs;
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};

use lb_domain::job::protocol::derived;
use lb_domain::results::{
    self, read_worker_files, EvalAiFiles, Expected, MergeOptions, MergeOutcome, ResultsError,
    ResultsFile, WorkerFile, WorkerInput, MAX_FILE_BYTES,
};
use tracing::{info, warn};

use crate::cli::MergeArgs;

/// The files `merge` writes, relative to its output directory.
pub const OUTPUTS: [&str; 4] = [
    derived::MERGED,
    derived::EVALAI_RESULTS,
    derived::EVALAI_STDOUT,
    derived::EVALAI_METADATA,
];

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
                println!(
                    "The statistics are badly formed. Setting their status to 'Invalid': {reason}"
                );
            }
            println!(
                "merged {} records from {} of {} files: {}, entry status {}, progress {}/{}",
                m.records.len(),
                files,
                args.files.len(),
                if outcome.complete {
                    "complete"
                } else {
                    "partial"
                },
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
        return Err(MergeError::SubsetCount {
            subsets: args.subsets.len(),
            files: args.files.len(),
        });
    }
    let names: Vec<String> = args.files.iter().map(|p| p.display().to_string()).collect();
    let contents = args
        .files
        .iter()
        .map(|p| read_limited(p))
        .collect::<Result<Vec<_>, _>>()?;
    let inputs: Vec<WorkerInput<'_>> = names
        .iter()
        .zip(&contents)
        .enumerate()
        .map(|(i, (name, bytes))| WorkerInput {
            source: name,
            bytes: bytes.as_deref(),
            subset: args.subsets.get(i).copied(),
        })
        .collect();
    let mut present: Vec<ResultsFile> = Vec::with_capacity(inputs.len());
    for (input, read) in inputs
        .iter()
        .zip(read_worker_files(&inputs, args.leaderboard))
    {
        match read? {
            WorkerFile::Present(file) => present.push(file),
            WorkerFile::Empty(reason) => {
                warn!(file = %input.source, %reason, "results file counts as empty")
            }
        }
    }
    let opts = MergeOptions {
        leaderboard: args.leaderboard,
        expected: args.expect_routes.map(|routes| Expected {
            routes,
            repetitions: args.repetitions,
        }),
    };
    let contributed = present.len();
    let outcome = results::merge(present, opts)?;
    info!(
        records = outcome.merged.records.len(),
        complete = outcome.complete,
        entry_status = %outcome.merged.entry_status,
        "results merged"
    );
    Ok((outcome, contributed))
}

/// The file's bytes, `None` if it does not exist; never reads more than the limit allows.
fn read_limited(path: &Path) -> Result<Option<Vec<u8>>, MergeError> {
    let read_err = |source| MergeError::Read {
        path: path.to_owned(),
        source,
    };
    let file = match fs::File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(read_err(e)),
    };
    // Sized from the metadata up front: growing a buffer by doubling costs page faults.
    let hint = file
        .metadata()
        .map_or(0, |m| m.len())
        .min(MAX_FILE_BYTES as u64 + 1);
    let mut bytes = Vec::with_capacity(hint as usize + 1);
    // One byte over the limit is enough for the parser to report the file as too large.
    file.take(MAX_FILE_BYTES as u64 + 1)
        .read_to_end(&mut bytes)
        .map_err(read_err)?;
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
    fs::create_dir(staging.path().join(derived::EVALAI_DIR)).map_err(write_err(staging.path()))?;

    let evalai = EvalAiFiles::generate(Some(&outcome.merged), leaderboard);
    // metadata.json is a copy of the merged file: serialize once, write twice.
    let merged = evalai.metadata.as_deref().unwrap_or_default();
    let results = evalai.results_json();
    let contents: [(&str, &str); 4] = [
        (OUTPUTS[0], merged),
        (OUTPUTS[1], &results),
        (OUTPUTS[2], &evalai.stdout),
        (OUTPUTS[3], merged),
    ];
    for (rel, text) in contents {
        let path = staging.path().join(rel);
        // NB: no fsync: these files are re-derivable from the workers' files, and the
        // rename below already keeps a reader from seeing a half-written one.
        fs::File::create(&path)
            .and_then(|mut f| f.write_all(text.as_bytes()))
            .map_err(write_err(&path))?;
    }
    for (rel, _) in contents {
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
