//! The image -> local command map: what each container image means on this machine.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;

/// Errors loading an image map.
#[derive(Debug, thiserror::Error)]
pub enum ImageMapError {
    /// The file could not be read.
    #[error("cannot read image map `{path}`: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The file is not a valid map.
    #[error("image map `{path}` is malformed: {message}")]
    Parse {
        /// The file (or `<inline>`).
        path: PathBuf,
        /// What the parser said.
        message: String,
    },
    /// An entry is unusable.
    #[error("image map entry `{image}`: {message}")]
    Entry {
        /// The image key.
        image: String,
        /// What is wrong.
        message: String,
    },
}

impl ImageMapError {
    /// Stable PascalCase name of the error.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Read { .. } => "ImageMapRead",
            Self::Parse { .. } => "ImageMapParse",
            Self::Entry { .. } => "ImageMapEntry",
        }
    }
}

/// Whether an image can be pulled.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Pull {
    /// The image is available (the default).
    #[default]
    Ok,
    /// The image cannot be pulled: `ErrImagePull`, then `ImagePullBackOff`.
    Fail,
}

/// What an image means locally.
#[derive(Clone, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "camelCase")]
pub struct ImageEntry {
    /// The image's ENTRYPOINT: run when the container gives no `command`.
    #[serde(default)]
    pub command: Option<Vec<String>>,
    /// The image's CMD: arguments when the container gives neither `command` nor `args`.
    #[serde(default)]
    pub args: Option<Vec<String>>,
    /// The image's ENV (the container's own `env` wins).
    #[serde(default)]
    pub env: BTreeMap<String, String>,
    /// The image's WORKDIR (the container's `workingDir` wins).
    #[serde(default)]
    pub working_dir: Option<String>,
    /// Host file or directory -> absolute path inside the container (bind-mounted).
    #[serde(default)]
    pub files: BTreeMap<PathBuf, String>,
    /// Host directories put in front of `PATH`.
    #[serde(default)]
    pub path: Vec<PathBuf>,
    /// `fail` makes the image unpullable.
    #[serde(default)]
    pub pull: Pull,
}

/// Image name (or pattern) -> entry, in file order.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ImageMap {
    entries: Vec<(String, ImageEntry)>,
}

fn glob(pattern: &str, text: &str) -> bool {
    let parts: Vec<&str> = pattern.split('*').collect();
    if parts.len() == 1 {
        return pattern == text;
    }
    let (first, last) = (parts[0], parts[parts.len() - 1]);
    if !text.starts_with(first) || text.len() < first.len() + last.len() || !text.ends_with(last) {
        return false;
    }
    let mut rest = &text[first.len()..text.len() - last.len()];
    for mid in &parts[1..parts.len() - 1] {
        match rest.find(mid) {
            Some(i) => rest = &rest[i + mid.len()..],
            None => return false,
        }
    }
    true
}

/// The image without its tag and digest (`repo/name`).
fn repository(image: &str) -> &str {
    let no_digest = image.split('@').next().unwrap_or(image);
    match no_digest.rfind(':') {
        Some(i) if !no_digest[i..].contains('/') => &no_digest[..i],
        _ => no_digest,
    }
}

impl ImageMap {
    /// Loads a YAML (or JSON) map; relative host paths in `files` and `path` are relative to the
    /// file's directory.
    pub fn from_path(path: &Path) -> Result<Self, ImageMapError> {
        let text = std::fs::read_to_string(path).map_err(|source| ImageMapError::Read {
            path: path.to_owned(),
            source,
        })?;
        let base = path.parent().unwrap_or(Path::new("."));
        Self::from_yaml(&text, base).map_err(|e| match e {
            ImageMapError::Parse { message, .. } => ImageMapError::Parse {
                path: path.to_owned(),
                message,
            },
            other => other,
        })
    }

    /// Parses a map from text; relative host paths are resolved against `base`.
    pub fn from_yaml(text: &str, base: &Path) -> Result<Self, ImageMapError> {
        let parse_err = |message: String| ImageMapError::Parse {
            path: PathBuf::from("<inline>"),
            message,
        };
        let value: serde_yaml::Value =
            serde_yaml::from_str(text).map_err(|e| parse_err(e.to_string()))?;
        let mapping = match value {
            serde_yaml::Value::Null => return Ok(Self::default()),
            serde_yaml::Value::Mapping(m) => m,
            _ => {
                return Err(parse_err(
                    "the top level must map image names to entries".into(),
                ))
            }
        };
        let mut map = Self::default();
        for (k, v) in mapping {
            let image = k
                .as_str()
                .ok_or_else(|| parse_err(format!("image names must be strings, got {k:?}")))?
                .to_owned();
            let mut entry: ImageEntry = if v.is_null() {
                ImageEntry::default()
            } else {
                serde_yaml::from_value(v).map_err(|e| ImageMapError::Entry {
                    image: image.clone(),
                    message: e.to_string(),
                })?
            };
            entry.files = entry
                .files
                .into_iter()
                .map(|(host, inside)| (base.join(host), inside))
                .collect();
            entry.path = entry.path.into_iter().map(|p| base.join(p)).collect();
            map.insert(image, entry)?;
        }
        Ok(map)
    }

    /// Adds (or replaces) an entry after checking it.
    pub fn insert(
        &mut self,
        image: impl Into<String>,
        entry: ImageEntry,
    ) -> Result<&mut Self, ImageMapError> {
        let image = image.into();
        let bad = |message: String| ImageMapError::Entry {
            image: image.clone(),
            message,
        };
        if image.is_empty() {
            return Err(bad("the image name is empty".into()));
        }
        if entry
            .command
            .as_ref()
            .is_some_and(|c| c.is_empty() || c[0].is_empty())
        {
            return Err(bad("`command` must name a program".into()));
        }
        if let Some(wd) = entry.working_dir.as_deref().filter(|w| !w.starts_with('/')) {
            return Err(bad(format!("`workingDir` `{wd}` must be absolute")));
        }
        for name in entry.env.keys() {
            if name.is_empty() || name.contains('=') {
                return Err(bad(format!("`env` name `{name}` is invalid")));
            }
        }
        for (host, inside) in &entry.files {
            if !host.exists() {
                return Err(bad(format!(
                    "`files` source `{}` does not exist",
                    host.display()
                )));
            }
            if !inside.starts_with('/') || inside.split('/').any(|p| p == "..") {
                return Err(bad(format!(
                    "`files` target `{inside}` must be an absolute path without `..`"
                )));
            }
        }
        for dir in &entry.path {
            if dir.to_str().is_none_or(|d| d.contains(':')) {
                return Err(bad(format!(
                    "`path` entry `{}` cannot go into PATH",
                    dir.display()
                )));
            }
        }
        self.entries.retain(|(k, _)| *k != image);
        self.entries.push((image, entry));
        Ok(self)
    }

    /// The entry for an image: the exact name, else the name without tag or digest, else the
    /// first `*` pattern that matches.
    pub fn lookup(&self, image: &str) -> Option<&ImageEntry> {
        let exact = self.entries.iter().find(|(k, _)| k == image);
        let repo = repository(image);
        let by_repo = || {
            self.entries
                .iter()
                .find(|(k, _)| !k.contains('*') && k == repo)
        };
        let by_glob = || {
            self.entries
                .iter()
                .find(|(k, _)| k.contains('*') && glob(k, image))
        };
        exact.or_else(by_repo).or_else(by_glob).map(|(_, e)| e)
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether the map is empty.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lookups_prefer_exact_then_repository_then_patterns() {
        let map = ImageMap::from_yaml(
            r#"
"carla:0.9.15": {command: [exact]}
carla: {command: [repo]}
"*.dkr.ecr.*.amazonaws.com/*": {command: [participant]}
"broken:1": {pull: fail}
"#,
            Path::new("/"),
        )
        .unwrap();
        let cmd = |i: &str| {
            map.lookup(i)
                .and_then(|e| e.command.clone())
                .map(|c| c[0].clone())
        };
        assert_eq!(cmd("carla:0.9.15").as_deref(), Some("exact"));
        assert_eq!(cmd("carla:0.9.14").as_deref(), Some("repo"));
        assert_eq!(cmd("carla").as_deref(), Some("repo"));
        assert_eq!(
            cmd("1.dkr.ecr.us-west-2.amazonaws.com/team:v1").as_deref(),
            Some("participant")
        );
        assert_eq!(cmd("other"), None);
        assert_eq!(map.lookup("broken:1").map(|e| e.pull), Some(Pull::Fail));
    }

    #[test]
    fn bad_entries_are_named_in_the_error() {
        let e = ImageMap::from_yaml("x: {comand: [a]}", Path::new("/")).unwrap_err();
        assert_eq!(e.name(), "ImageMapEntry");
        assert!(e.to_string().contains("`x`"), "{e}");
        let e = ImageMap::from_yaml("y: {files: {/no/such/file: /a}}", Path::new("/")).unwrap_err();
        assert!(e.to_string().contains("/no/such/file"), "{e}");
        let e = ImageMap::from_yaml("- a", Path::new("/")).unwrap_err();
        assert_eq!(e.name(), "ImageMapParse");
    }

    #[test]
    fn relative_host_paths_are_relative_to_the_map_file() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("fake.sh"), "#!/bin/sh\n").unwrap();
        let file = dir.path().join("images.json");
        std::fs::write(
            &file,
            r#"{"carla": {"files": {"fake.sh": "/home/carla/CarlaUE4.sh"}, "path": ["bin"], "env": {"A": "1"}}}"#,
        )
        .unwrap();
        let map = ImageMap::from_path(&file).unwrap();
        let e = map.lookup("carla:1").unwrap();
        assert_eq!(e.files.keys().next().unwrap(), &dir.path().join("fake.sh"));
        assert_eq!(e.path, vec![dir.path().join("bin")]);
        assert_eq!(e.env.get("A").map(String::as_str), Some("1"));
    }
}
