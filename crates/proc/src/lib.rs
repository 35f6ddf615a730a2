//! Linux processes as `/proc` shows them: a process's live descendants.
//!
//! The sidecar stops every process its child left (whatever it did to escape its group), and
//! the rehearsal finds the CARLA a pod started: both walk the same tree.

use std::fs;

use nix::unistd::Pid;

/// The live descendants of `root` (not `root` itself), from `/proc`; none when `/proc` cannot
/// be read.
pub fn descendants(root: Pid) -> Vec<Pid> {
    let Ok(entries) = fs::read_dir("/proc") else {
        return Vec::new();
    };
    let mut parent_of: Vec<(i32, i32)> = Vec::new();
    for entry in entries.flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<i32>().ok())
        else {
            continue;
        };
        if let Ok(stat) = fs::read_to_string(entry.path().join("stat")) {
            if let Some((ppid, state)) = parse_stat(&stat) {
                // NB: zombies are gone already; they only wait to be reaped.
                if state != 'Z' {
                    parent_of.push((pid, ppid));
                }
            }
        }
    }
    let mut found = vec![root.as_raw()];
    let mut i = 0;
    while i < found.len() {
        let parent = found[i];
        for &(pid, ppid) in &parent_of {
            if ppid == parent && !found.contains(&pid) {
                found.push(pid);
            }
        }
        i += 1;
    }
    found.into_iter().skip(1).map(Pid::from_raw).collect()
}

/// `(ppid, state)` from `/proc/<pid>/stat`; the command name may hold spaces and parentheses,
/// so the fields are read after its last `)`.
fn parse_stat(stat: &str) -> Option<(i32, char)> {
    let rest = &stat[stat.rfind(')')? + 1..];
    let mut fields = rest.split_whitespace();
    let state = fields.next()?.chars().next()?;
    let ppid = fields.next()?.parse().ok()?;
    Some((ppid, state))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stat_lines_with_odd_command_names_parse() {
        assert_eq!(
            parse_stat("1234 (a) b (c)) S 77 1234 1234 0 -1"),
            Some((77, 'S'))
        );
        assert_eq!(parse_stat("5 (sh) Z 1 5 5"), Some((1, 'Z')));
        assert_eq!(parse_stat("garbage"), None);
    }

    #[test]
    fn a_child_is_a_descendant_and_the_root_is_not() {
        let mut child = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let me = nix::unistd::getpid();
        let found = descendants(me);
        let _ = child.kill();
        let _ = child.wait();
        assert!(
            found.contains(&Pid::from_raw(child.id() as i32)),
            "{found:?}"
        );
        assert!(!found.contains(&me));
    }
}
