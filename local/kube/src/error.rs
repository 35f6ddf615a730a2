//! Errors of starting and running the server.

use std::path::PathBuf;

use crate::imagemap::ImageMapError;

/// What can go wrong starting or stopping local-kube.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The listen address could not be bound.
    #[error("cannot listen on `{addr}`: {source}")]
    Bind {
        /// The address.
        addr: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The state directory could not be prepared.
    #[error("cannot prepare state directory `{path}`: {source}")]
    StateDir {
        /// The directory.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// Mount-namespace isolation was required but is unavailable.
    #[error("mount namespace isolation is unavailable: {0}")]
    Isolation(String),
    /// The image map is unusable.
    #[error(transparent)]
    ImageMap(#[from] ImageMapError),
    /// Writing the kubeconfig failed.
    #[error("cannot write kubeconfig `{path}`: {source}")]
    Kubeconfig {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The server thread or runtime failed.
    #[error("server runtime failed: {0}")]
    Runtime(String),
}

impl Error {
    /// Stable PascalCase name of the error.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Bind { .. } => "Bind",
            Self::StateDir { .. } => "StateDir",
            Self::Isolation(_) => "Isolation",
            Self::ImageMap(e) => e.name(),
            Self::Kubeconfig { .. } => "Kubeconfig",
            Self::Runtime(_) => "Runtime",
        }
    }
}

/// Result with this crate's error.
pub type Result<T, E = Error> = std::result::Result<T, E>;
