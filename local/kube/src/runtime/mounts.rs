//! Bind-mount plans for a container (volumes, subPaths, image files) and the mount points
//! that must exist before binding.

use std::io;
use std::path::{Path, PathBuf};

/// One bind mount: host `src` appears at `dst` inside the container.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Mount {
    /// Host path.
    pub src: PathBuf,
    /// Path inside the container.
    pub dst: PathBuf,
    /// Remounted read-only.
    pub read_only: bool,
}

/// What a container needs before it starts.
#[derive(Debug, Default)]
pub struct Plan {
    /// Mounts, parents before children.
    pub mounts: Vec<Mount>,
    /// Paths this plan had to create (mount points, working directory).
    pub created: Vec<PathBuf>,
}

/// Makes `path` exist (a directory, or an empty file when `file`), creating missing
/// components; returns what it created.
///
/// NB: created mount points are left in place (empty), as a container runtime leaves them in
/// its rootfs: removing one while another server's container has it mounted in its own
/// namespace would silently detach that mount.
pub fn ensure(path: &Path, file: bool) -> io::Result<Vec<PathBuf>> {
    let mut created = Vec::new();
    let parts: Vec<&Path> = path.ancestors().collect();
    for (i, p) in parts.iter().rev().enumerate() {
        if p.parent().is_none() {
            continue;
        }
        let want_file = file && i == parts.len() - 1;
        match std::fs::metadata(p) {
            Ok(m) if m.is_dir() && want_file => {
                return Err(io::Error::other(format!(
                    "`{}` is a directory but a file is mounted there",
                    p.display()
                )))
            }
            Ok(m) if !m.is_dir() && !want_file => {
                return Err(io::Error::other(format!(
                    "`{}` is a file but a directory is needed there",
                    p.display()
                )))
            }
            Ok(_) => {}
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                if want_file {
                    std::fs::File::create(p)?;
                } else {
                    // NB: another container may create it at the same moment.
                    match std::fs::create_dir(p) {
                        Err(e) if e.kind() != io::ErrorKind::AlreadyExists => return Err(e),
                        _ => {}
                    }
                }
                created.push(p.to_path_buf());
            }
            Err(e) => return Err(e),
        }
    }
    Ok(created)
}

/// Orders the mounts and creates their mount points (inside a parent mount's source when
/// nested) and the working directory.
pub fn plan(mut mounts: Vec<Mount>, workdir: &Path) -> Result<Plan, String> {
    for m in &mounts {
        if !m.dst.is_absolute() {
            return Err(format!("mount path `{}` must be absolute", m.dst.display()));
        }
        if !m.src.exists() {
            return Err(format!("mount source `{}` does not exist", m.src.display()));
        }
    }
    mounts.sort_by_key(|m| m.dst.components().count());
    let mut out = Plan::default();
    for i in 0..mounts.len() {
        let m = &mounts[i];
        let host_point = host_location(&mounts[..i], &m.dst).unwrap_or_else(|| m.dst.clone());
        let made = ensure(&host_point, m.src.is_file())
            .map_err(|e| format!("cannot create mount point `{}`: {e}", m.dst.display()))?;
        out.created.extend(made);
    }
    let wd_host = host_location(&mounts, workdir).unwrap_or_else(|| workdir.to_owned());
    let made = ensure(&wd_host, false).map_err(|e| {
        format!(
            "cannot create working directory `{}`: {e}",
            workdir.display()
        )
    })?;
    out.created.extend(made);
    out.mounts = mounts;
    Ok(out)
}

/// Where a container path lives on the host when it falls under one of `mounts` (the deepest).
fn host_location(mounts: &[Mount], path: &Path) -> Option<PathBuf> {
    mounts
        .iter()
        .filter(|p| path.starts_with(&p.dst) && path != p.dst)
        .max_by_key(|p| p.dst.components().count())
        .and_then(|p| path.strip_prefix(&p.dst).ok().map(|rel| p.src.join(rel)))
        .or_else(|| mounts.iter().find(|p| path == p.dst).map(|p| p.src.clone()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_components_are_created_and_reported() {
        let dir = tempfile::tempdir().unwrap();
        let made = ensure(&dir.path().join("a/b/c"), false).unwrap();
        assert_eq!(made.len(), 3);
        assert!(dir.path().join("a/b/c").is_dir());
        assert!(ensure(&dir.path().join("a/b/c"), false).unwrap().is_empty());
        let file = ensure(&dir.path().join("f/x.sh"), true).unwrap();
        assert_eq!(file.len(), 2);
        assert!(dir.path().join("f/x.sh").is_file());
    }

    #[test]
    fn type_clashes_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("file"), "x").unwrap();
        assert!(ensure(&dir.path().join("file"), false).is_err());
        assert!(ensure(dir.path(), true).is_err());
    }

    #[test]
    fn nested_mount_points_are_made_inside_the_parent_source() {
        let host = tempfile::tempdir().unwrap();
        let vol = host.path().join("vol");
        let sub = host.path().join("sub");
        std::fs::create_dir_all(&vol).unwrap();
        std::fs::create_dir_all(&sub).unwrap();
        let root = host.path().join("ctr");
        let mounts = vec![
            Mount {
                src: sub.clone(),
                dst: root.join("w/inner"),
                read_only: true,
            },
            Mount {
                src: vol.clone(),
                dst: root.join("w"),
                read_only: false,
            },
        ];
        let plan = plan(mounts, &root.join("w/cwd")).unwrap();
        assert_eq!(plan.mounts[0].dst, root.join("w"));
        assert!(
            vol.join("inner").is_dir(),
            "nested mount point made in the volume"
        );
        assert!(vol.join("cwd").is_dir(), "working dir made in the volume");
        assert!(!root.join("w/inner").exists());
        assert!(root.join("w").is_dir());
    }
}
