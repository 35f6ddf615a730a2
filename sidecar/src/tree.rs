//! The logs tree as logcopy sees it: a bounded walk, and what changed since the last upload.
//!
//! The tree holds files the participant's code wrote, so it is hostile: symbolic links are
//! never followed, files are opened component by component with `O_NOFOLLOW` and must be
//! regular files on the logs volume itself (same device as the root), which keeps a planted
//! link to a token or another mount from being uploaded. Counts, depth and key lengths are bounded.

use std::collections::HashMap;
use std::fs::{self, File, OpenOptions};
use std::io::{self, Read};
use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use lb_domain::job::protocol::{PairId, STATUS_DIR};
use nix::fcntl::OFlag;
use sha2::{Digest, Sha256};

/// At most this many files are tracked; more are ignored (and reported).
pub const MAX_FILES: usize = 100_000;
/// Directories deeper than this are not walked.
pub const MAX_DEPTH: usize = 16;
/// Longest relative path uploaded (S3 keys are at most 1,024 bytes with the prefix).
pub const MAX_KEY_BYTES: usize = 900;
/// A file modified this recently may still change within its timestamp's granularity, so
/// its metadata alone is not trusted next time (git's "racily clean" rule).
const RACY: Duration = Duration::from_secs(2);

/// A regular file found by [`scan`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Entry {
    /// Path relative to the root, `/`-separated: the key suffix.
    pub rel: String,
    /// Full path.
    pub path: PathBuf,
    /// Its metadata at scan time.
    pub meta: FileMeta,
}

/// What identifies a version of a file without reading it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FileMeta {
    /// Size in bytes.
    pub size: u64,
    /// Modification time, nanoseconds since the epoch.
    pub mtime_ns: i128,
    /// Inode (a replaced file is a new one).
    pub ino: u64,
}

impl FileMeta {
    fn of(m: &fs::Metadata) -> FileMeta {
        FileMeta {
            size: m.len(),
            mtime_ns: i128::from(m.mtime()) * 1_000_000_000 + i128::from(m.mtime_nsec()),
            ino: m.ino(),
        }
    }

    /// Whether the file changed so recently that the same metadata may hide a later write.
    fn racy(&self, now: SystemTime) -> bool {
        let now_ns = now
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as i128);
        now_ns - self.mtime_ns < RACY.as_nanos() as i128
    }
}

/// What a walk left out, for the logs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Skipped {
    /// Symbolic links, devices, sockets, FIFOs, other mounts.
    pub not_regular: usize,
    /// Names that are not clean UTF-8 or make too long a key.
    pub bad_names: usize,
    /// Files beyond [`MAX_FILES`] or directories beyond [`MAX_DEPTH`].
    pub over_limits: usize,
}

/// Walks the tree under `root` (on device `dev`), sorted so that `containers-status/` comes
/// last: the markers must never reach S3 before the results and logs they vouch for.
pub fn scan(root: &Path, dev: u64) -> io::Result<(Vec<Entry>, Skipped)> {
    let mut entries = Vec::new();
    let mut skipped = Skipped::default();
    walk(root, "", dev, 0, &mut entries, &mut skipped)?;
    entries.sort_by(|a, b| {
        let status = |e: &Entry| {
            e.rel
                .strip_prefix(STATUS_DIR)
                .is_some_and(|rest| rest.starts_with('/'))
        };
        status(a).cmp(&status(b)).then_with(|| a.rel.cmp(&b.rel))
    });
    Ok((entries, skipped))
}

fn walk(
    dir: &Path,
    prefix: &str,
    dev: u64,
    depth: usize,
    out: &mut Vec<Entry>,
    skipped: &mut Skipped,
) -> io::Result<()> {
    let listing = match fs::read_dir(dir) {
        Ok(l) => l,
        // A directory removed under us (or unreadable) is not worth failing the pass for,
        // except the root itself.
        Err(e) if depth > 0 => {
            tracing::debug!(dir = %dir.display(), error = %e, "cannot list a directory");
            return Ok(());
        }
        Err(e) => return Err(e),
    };
    for item in listing {
        let Ok(item) = item else { continue };
        let Some(name) = item.file_name().to_str().map(str::to_owned) else {
            skipped.bad_names += 1;
            continue;
        };
        let rel = if prefix.is_empty() {
            name.clone()
        } else {
            format!("{prefix}/{name}")
        };
        if !key_ok(&name) || rel.len() > MAX_KEY_BYTES {
            skipped.bad_names += 1;
            continue;
        }
        // NB: DirEntry::metadata does not follow symbolic links.
        let Ok(meta) = item.metadata() else { continue };
        if meta.dev() != dev {
            skipped.not_regular += 1;
        } else if meta.is_dir() {
            if depth + 1 >= MAX_DEPTH {
                skipped.over_limits += 1;
            } else {
                walk(&item.path(), &rel, dev, depth + 1, out, skipped)?;
            }
        } else if meta.is_file() {
            if out.len() >= MAX_FILES {
                skipped.over_limits += 1;
            } else {
                out.push(Entry {
                    rel,
                    path: item.path(),
                    meta: FileMeta::of(&meta),
                });
            }
        } else {
            skipped.not_regular += 1;
        }
    }
    Ok(())
}

/// The files whose upload wakes the submission's Monitor (`lb_domain::job::protocol::
/// wakes_submission`): the workers' results files directly under `agent/`, then the markers
/// under `containers-status/` (results before markers, as in [`scan`], so a done marker never
/// lands before the results it vouches for). Two directory listings, no walk: cheap enough
/// to run every second between full passes.
pub fn scan_wake_worthy(root: &Path, dev: u64) -> Vec<Entry> {
    let results = |name: &str| lb_domain::job::protocol::pair_of_results_name(name).is_some();
    let mut out = list_dir(root, lb_domain::job::protocol::AGENT_DIR, dev, results);
    out.extend(list_dir(root, STATUS_DIR, dev, |_| true));
    out
}

/// The regular files on the logs volume directly in `dir` whose names `keep` takes, by name
/// (at most [`MAX_FILES`]; none when `dir` cannot be listed).
fn list_dir(root: &Path, dir: &str, dev: u64, keep: impl Fn(&str) -> bool) -> Vec<Entry> {
    let Ok(listing) = fs::read_dir(root.join(dir)) else {
        return Vec::new();
    };
    let mut found: Vec<Entry> = listing
        .filter_map(Result::ok)
        .filter_map(|item| {
            let name = item.file_name().to_str()?.to_owned();
            let meta = item.metadata().ok()?;
            let regular = meta.is_file() && meta.dev() == dev;
            (regular && key_ok(&name) && keep(&name)).then(|| Entry {
                rel: format!("{dir}/{name}"),
                path: item.path(),
                meta: FileMeta::of(&meta),
            })
        })
        .take(MAX_FILES)
        .collect();
    found.sort_by(|a, b| a.rel.cmp(&b.rel));
    found
}

/// The recordings of these pairs that CARLA has finished: in each pair's folder
/// (`recorder/pair<ID>`), every recording but the last modified, since a simulator records one
/// route at a time and starts the next route's file only after it stopped the last. Uploaded
/// between passes, so a pod lost at once (a node gone without notice) loses no finished
/// route's recording while its results, uploaded within a second, stand. The last one, and a
/// folder's newest tied in time, wait for the period. One listing per pair, no walk.
pub fn scan_finished_recordings(root: &Path, dev: u64, pairs: &[PairId]) -> Vec<Entry> {
    let mut out = Vec::new();
    for &pair in pairs {
        let dir = lb_domain::job::protocol::recorder_dir(pair);
        let recording = |name: &str| {
            lb_domain::job::protocol::kept_as(&format!("{dir}/{name}"), &[pair]).is_some()
        };
        out.extend(superseded(list_dir(root, &dir, dev, recording)));
    }
    out
}

/// All but the last modified of one folder's recordings (none when the newest time is shared:
/// which is being written is then unknown), by name.
fn superseded(mut found: Vec<Entry>) -> Vec<Entry> {
    let Some(newest) = found.iter().map(|e| e.meta.mtime_ns).max() else {
        return found;
    };
    found.retain(|e| e.meta.mtime_ns < newest);
    found.sort_by(|a, b| a.rel.cmp(&b.rel));
    found
}

/// A name that is safe as part of an S3 key and a local path: printable, not `.`/`..`. No
/// invisible format character either (bidirectional controls, zero-width ones): a key that
/// reads as another in the console or `lbctl logs` would hide what the participant wrote.
pub fn key_ok(name: &str) -> bool {
    !name.is_empty()
        && name != "."
        && name != ".."
        && !name.contains('/')
        && !name
            .chars()
            .any(|c| c.is_control() || lb_domain::job::logtail::is_invisible_format(c))
}

/// A key suffix that is safe to turn into a local path (init's downloads).
pub fn rel_path_ok(rel: &str) -> bool {
    rel.len() <= MAX_KEY_BYTES && !rel.starts_with('/') && rel.split('/').all(key_ok)
}

/// Opens the file at `rel` (a walk's relative path) under `root`, one component at a time:
/// each directory with `openat(O_DIRECTORY | O_NOFOLLOW)` from the one before, the file with
/// `O_NOFOLLOW`. A directory swapped for a symbolic link between the walk and this open (the
/// participant's code runs meanwhile) fails the open instead of leading outside the tree, as a
/// path opened whole would. Non-regular files and other devices are refused too. Returns the
/// open file and its metadata now.
pub fn open_checked(root: &Path, rel: &str, dev: u64) -> io::Result<(File, FileMeta)> {
    use nix::sys::stat::Mode;
    use std::os::fd::OwnedFd;

    if !rel_path_ok(rel) {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "not a clean relative path",
        ));
    }
    let open_dir = OFlag::O_RDONLY | OFlag::O_DIRECTORY | OFlag::O_NOFOLLOW | OFlag::O_CLOEXEC;
    // The root is ours (the configured logs volume), not the participant's.
    let mut dir: OwnedFd = OpenOptions::new()
        .read(true)
        .custom_flags((OFlag::O_DIRECTORY | OFlag::O_CLOEXEC).bits())
        .open(root)?
        .into();
    let mut components = rel.split('/').peekable();
    let mut file = None;
    while let Some(name) = components.next() {
        if components.peek().is_some() {
            dir =
                nix::fcntl::openat(&dir, name, open_dir, Mode::empty()).map_err(io::Error::from)?;
        } else {
            let flags = OFlag::O_RDONLY | OFlag::O_NOFOLLOW | OFlag::O_NONBLOCK | OFlag::O_CLOEXEC;
            file = Some(File::from(
                nix::fcntl::openat(&dir, name, flags, Mode::empty()).map_err(io::Error::from)?,
            ));
        }
    }
    let file = file.ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "empty path"))?;
    let meta = file.metadata()?;
    if !meta.is_file() || meta.dev() != dev {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "not a regular file on the logs volume",
        ));
    }
    Ok((file, FileMeta::of(&meta)))
}

/// SHA-256 of `size` bytes of a file, read with a small buffer.
pub fn hash_file(file: &mut File, size: u64) -> io::Result<[u8; 32]> {
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 64 * 1024];
    let mut limited = file.take(size);
    loop {
        let n = limited.read(&mut buf)?;
        if n == 0 {
            return Ok(hasher.finalize().into());
        }
        hasher.update(&buf[..n]);
    }
}

/// The version of a file last uploaded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Uploaded {
    /// Metadata when it was read for the upload.
    pub meta: FileMeta,
    /// SHA-256 of the bytes sent.
    pub hash: [u8; 32],
    /// Whether the metadata was too fresh to be trusted.
    pub racy: bool,
}

/// What to do with a file this pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Action {
    /// Same metadata as the uploaded version: not even opened.
    Skip,
    /// Same size, other metadata (or racy): hash it, upload only if the content differs.
    Compare,
    /// New or resized: upload.
    Upload,
}

/// Decides from metadata alone; no file is read for an unchanged one.
pub fn action(last: Option<&Uploaded>, now: &FileMeta) -> Action {
    match last {
        None => Action::Upload,
        Some(u) if u.meta == *now && !u.racy => Action::Skip,
        Some(u) if u.meta.size == now.size => Action::Compare,
        Some(_) => Action::Upload,
    }
}

/// The uploaded versions, by relative path.
#[derive(Debug, Default)]
pub struct Tracker {
    uploaded: HashMap<String, Uploaded>,
}

impl Tracker {
    /// The last uploaded version of a file.
    pub fn get(&self, rel: &str) -> Option<&Uploaded> {
        self.uploaded.get(rel)
    }

    /// Records a version as uploaded (only ever after S3 said so).
    pub fn record(&mut self, rel: &str, meta: FileMeta, hash: [u8; 32]) {
        let racy = meta.racy(SystemTime::now());
        self.uploaded
            .insert(rel.to_owned(), Uploaded { meta, hash, racy });
    }

    /// Forgets files that are gone, so the map never outgrows the tree.
    pub fn retain_present(&mut self, entries: &[Entry]) {
        if self.uploaded.len() > entries.len() {
            let present: std::collections::HashSet<&str> =
                entries.iter().map(|e| e.rel.as_str()).collect();
            self.uploaded.retain(|k, _| present.contains(k.as_str()));
        }
    }

    /// How many files are tracked.
    pub fn len(&self) -> usize {
        self.uploaded.len()
    }

    /// Whether nothing is tracked.
    pub fn is_empty(&self) -> bool {
        self.uploaded.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::symlink;

    fn meta(size: u64, mtime_ns: i128) -> FileMeta {
        FileMeta {
            size,
            mtime_ns,
            ino: 7,
        }
    }

    #[test]
    fn only_recordings_older_than_the_newest_are_finished() {
        let entry = |name: &str, mtime_ns| Entry {
            rel: format!("recorder/pair1/{name}"),
            path: PathBuf::from(name),
            meta: meta(1, mtime_ns),
        };
        let names = |found: Vec<Entry>| found.into_iter().map(|e| e.rel).collect::<Vec<_>>();
        let folder = vec![
            entry("R_2.log", 30),
            entry("R_0.log", 10),
            entry("R_1.log", 20),
        ];
        assert_eq!(
            names(superseded(folder)),
            ["recorder/pair1/R_0.log", "recorder/pair1/R_1.log"]
        );
        // The newest time shared: either may be the one being written; both wait.
        let tied = vec![
            entry("R_0.log", 10),
            entry("R_1.log", 20),
            entry("R_2.log", 20),
        ];
        assert_eq!(names(superseded(tied)), ["recorder/pair1/R_0.log"]);
        assert!(superseded(vec![entry("R_0.log", 10)]).is_empty());
        assert!(superseded(Vec::new()).is_empty());
    }

    #[test]
    fn a_key_refuses_controls_and_invisible_format_characters() {
        for name in ["agent.log", "données.txt", "日本.log", "R_0.log"] {
            assert!(key_ok(name), "{name}");
        }
        for name in [
            "",
            ".",
            "..",
            "a/b",
            "a\nb",
            "a\u{1b}[2Jb",
            "gol.exe\u{202e}txt",
            "a\u{200b}b",
            "a\u{2066}b",
            "a\u{feff}b",
        ] {
            assert!(!key_ok(name), "{name:?}");
        }
    }

    #[test]
    fn unchanged_metadata_is_skipped_without_reading() {
        let u = Uploaded {
            meta: meta(10, 5),
            hash: [0; 32],
            racy: false,
        };
        assert_eq!(action(Some(&u), &meta(10, 5)), Action::Skip);
        assert_eq!(action(Some(&u), &meta(10, 6)), Action::Compare);
        assert_eq!(action(Some(&u), &meta(11, 6)), Action::Upload);
        assert_eq!(action(None, &meta(10, 5)), Action::Upload);
        let racy = Uploaded { racy: true, ..u };
        assert_eq!(action(Some(&racy), &meta(10, 5)), Action::Compare);
    }

    #[test]
    fn the_walk_skips_links_and_puts_the_markers_last() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        fs::create_dir_all(root.join("containers-status")).unwrap();
        fs::create_dir_all(root.join("logs/agent/agent1")).unwrap();
        fs::write(root.join("containers-status/agent-1.done"), "").unwrap();
        fs::write(root.join("logs/agent/agent1/agent.log"), "hello").unwrap();
        fs::write(root.join("z.txt"), "z").unwrap();
        symlink("/etc/passwd", root.join("logs/agent/agent1/secret")).unwrap();
        symlink("/etc", root.join("logs/etc")).unwrap();
        let dev = fs::metadata(root).unwrap().dev();
        let (entries, skipped) = scan(root, dev).unwrap();
        let rels: Vec<&str> = entries.iter().map(|e| e.rel.as_str()).collect();
        assert_eq!(
            rels,
            [
                "logs/agent/agent1/agent.log",
                "z.txt",
                "containers-status/agent-1.done"
            ]
        );
        assert_eq!(skipped.not_regular, 2);
        assert!(open_checked(root, "logs/agent/agent1/secret", dev).is_err());
        assert!(open_checked(root, "logs/agent/agent1/agent.log", dev).is_ok());
    }

    #[test]
    fn a_directory_swapped_for_a_link_after_the_walk_leads_nowhere() {
        // The participant's code replaces `logs/agent` with a link to a tree outside the logs
        // (on the same device) between logcopy's walk and its open.
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("root");
        let outside = dir.path().join("outside");
        fs::create_dir_all(root.join("logs/agent/agent1")).unwrap();
        fs::create_dir_all(outside.join("agent1")).unwrap();
        fs::write(root.join("logs/agent/agent1/agent.log"), "mine").unwrap();
        fs::write(outside.join("agent1/agent.log"), "the secret routes").unwrap();
        let dev = fs::metadata(&root).unwrap().dev();
        let (entries, _) = scan(&root, dev).unwrap();
        assert_eq!(entries[0].rel, "logs/agent/agent1/agent.log");

        fs::rename(root.join("logs/agent"), dir.path().join("moved")).unwrap();
        symlink(&outside, root.join("logs/agent")).unwrap();
        // Opening the path whole would follow the link and read "the secret routes".
        assert_eq!(
            fs::read_to_string(root.join(&entries[0].rel)).unwrap(),
            "the secret routes"
        );
        let err = open_checked(&root, &entries[0].rel, dev).unwrap_err();
        let code = err.raw_os_error();
        assert!(
            code == Some(nix::errno::Errno::ELOOP as i32)
                || code == Some(nix::errno::Errno::ENOTDIR as i32),
            "{err}"
        );
    }

    #[test]
    fn keys_from_s3_never_escape_the_local_tree() {
        assert!(rel_path_ok("logs/agent/agent1/agent.log"));
        for bad in [
            "../x",
            "/etc/passwd",
            "logs/../../x",
            "logs//x",
            "logs/./x",
            "a\nb",
            "",
        ] {
            assert!(!rel_path_ok(bad), "{bad:?}");
        }
    }

    #[test]
    fn hashing_reads_only_the_given_size() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        fs::write(&path, "abcdef").unwrap();
        let mut f = File::open(&path).unwrap();
        let short = hash_file(&mut f, 3).unwrap();
        let expected: [u8; 32] = Sha256::digest(b"abc").into();
        assert_eq!(short, expected);
    }
}
