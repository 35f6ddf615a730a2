//! The status directory on disk: listing, writing and removing marker files.

use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use lb_domain::job::protocol::{Marker, Markers};

/// A `containers-status` directory.
#[derive(Debug, Clone)]
pub struct StatusDir {
    path: PathBuf,
}

impl StatusDir {
    /// The directory at `path` (created on first write if missing).
    pub fn new(path: impl Into<PathBuf>) -> StatusDir {
        StatusDir { path: path.into() }
    }

    /// Where it is.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The markers present now; a missing directory has none.
    pub fn markers(&self) -> io::Result<Markers> {
        let entries = match fs::read_dir(&self.path) {
            Ok(entries) => entries,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Markers::default()),
            Err(e) => return Err(e),
        };
        let mut names = Vec::new();
        for entry in entries {
            // NB: names that are not UTF-8 cannot be markers.
            if let Ok(name) = entry?.file_name().into_string() {
                names.push(name);
            }
        }
        Ok(Markers::from_names(names.iter().map(String::as_str)))
    }

    /// Writes a marker (an empty file); writing one that exists is a no-op.
    pub fn write(&self, marker: Marker) -> io::Result<()> {
        fs::create_dir_all(&self.path)?;
        fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(self.path.join(marker.to_string()))?;
        tracing::info!(%marker, dir = %self.path.display(), "marker written");
        Ok(())
    }

    /// Removes a marker; a missing one is fine.
    pub fn remove(&self, marker: Marker) -> io::Result<()> {
        match fs::remove_file(self.path.join(marker.to_string())) {
            Ok(()) => {
                tracing::info!(%marker, dir = %self.path.display(), "marker removed");
                Ok(())
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e),
        }
    }

    /// Whether a marker is present.
    pub fn contains(&self, marker: Marker) -> bool {
        self.path.join(marker.to_string()).exists()
    }
}
