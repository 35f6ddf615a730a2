//! What the real evaluator imports before it runs a route, checked against `PYTHONPATH`.
//!
//! `leaderboard_evaluator.py` does `import carla` and imports `leaderboard.*` and `srunner.*`
//! at module level, then `LeaderboardEvaluator.__init__` imports the participant's agent
//! module, whose own imports come from the code root the participant's image put on
//! `PYTHONPATH`. Any of them missing is an uncaught `ModuleNotFoundError`: a traceback and
//! exit 1. The fake checks the same, so a Job template that replaces the image's
//! `PYTHONPATH` or names the CARLA egg wrongly fails here as it would on the cluster.

use std::path::Path;

use crate::args::Env;

/// The paths that decide what imports succeed.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Imports {
    /// `PYTHONPATH`, split on `:`.
    pub python_path: Vec<String>,
    /// `CARLA_ROOT`: when set, an egg of the CARLA PythonAPI (`*py3*.egg`) must be on the path.
    pub carla_root: Option<String>,
    /// `LEADERBOARD_ROOT`: when set, it must be on the path.
    pub leaderboard_root: Option<String>,
    /// `SCENARIO_RUNNER_ROOT`: when set, it must be on the path.
    pub scenario_runner_root: Option<String>,
    /// `FAKE_EVALUATOR_TEAM_CODE`: the code root the participant's agent imports from.
    pub team_code: Option<String>,
}

/// A failed import: the traceback's innermost frame and the exception line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ImportFailure {
    /// `(function, code)` of the frame that imported.
    pub frame: (&'static str, &'static str),
    /// `ModuleNotFoundError: No module named '...'`.
    pub error: String,
}

impl Imports {
    /// Reads the evaluator's environment.
    pub fn from_env(env: &Env) -> Imports {
        let owned = |key: &str| env.non_empty(key).map(str::to_owned);
        Imports {
            python_path: env
                .get("PYTHONPATH")
                .unwrap_or_default()
                .split(':')
                .filter(|p| !p.is_empty())
                .map(str::to_owned)
                .collect(),
            carla_root: owned("CARLA_ROOT"),
            leaderboard_root: owned("LEADERBOARD_ROOT"),
            scenario_runner_root: owned("SCENARIO_RUNNER_ROOT"),
            team_code: owned("FAKE_EVALUATOR_TEAM_CODE"),
        }
    }

    fn on_path(&self, dir: &str) -> bool {
        let dir = dir.trim_end_matches('/');
        self.python_path
            .iter()
            .any(|p| p.trim_end_matches('/') == dir)
    }

    fn has_carla_egg(&self) -> bool {
        self.python_path.iter().any(|p| {
            let path = Path::new(p);
            let name = path
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or_default();
            name.ends_with(".egg") && name.contains("py3") && path.is_file()
        })
    }

    /// The first import that would fail, in the order Python runs them.
    pub fn check(&self) -> Result<(), ImportFailure> {
        let missing = |frame, module: &str| {
            Err(ImportFailure {
                frame,
                error: format!("ModuleNotFoundError: No module named '{module}'"),
            })
        };
        const MODULE: (&str, &str) = ("<module>", "import carla");
        if self.carla_root.is_some() && !self.has_carla_egg() {
            return missing(MODULE, "carla");
        }
        // The evaluator's own imports, in its order: ScenarioRunner, then the Leaderboard.
        for (root, line, module) in [
            (
                &self.scenario_runner_root,
                "from srunner.scenariomanager.carla_data_provider import *",
                "srunner",
            ),
            (
                &self.leaderboard_root,
                "from leaderboard.scenarios.scenario_manager import ScenarioManager",
                "leaderboard",
            ),
        ] {
            if root.as_ref().is_some_and(|r| !self.on_path(r)) {
                return missing(("<module>", line), module);
            }
        }
        if let Some(root) = &self.team_code {
            if !self.on_path(root) {
                let module = Path::new(root)
                    .file_name()
                    .and_then(|n| n.to_str())
                    .unwrap_or("team_code")
                    .to_owned();
                return missing(
                    (
                        "__init__",
                        "self.module_agent = importlib.import_module(module_name)",
                    ),
                    &module,
                );
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job_env(python_path: &str, egg: &Path) -> Imports {
        let mut path = vec![egg.display().to_string()];
        path.extend(python_path.split(':').map(str::to_owned));
        Imports {
            python_path: path,
            carla_root: Some("/workspace/CARLA".into()),
            leaderboard_root: Some("/workspace/leaderboard".into()),
            scenario_runner_root: Some("/workspace/scenario_runner".into()),
            team_code: Some("/opt/team_code".into()),
        }
    }

    fn egg(dir: &Path, name: &str) -> std::path::PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, b"egg").unwrap();
        path
    }

    #[test]
    fn the_official_code_prepended_to_the_images_path_imports_everything() {
        let dir = tempfile::tempdir().unwrap();
        let egg = egg(dir.path(), "carla-leaderboard-py3x.egg");
        let imports = job_env(
            "/workspace/scenario_runner:/workspace/leaderboard:/opt/team_code",
            &egg,
        );
        assert_eq!(imports.check(), Ok(()));
    }

    #[test]
    fn a_path_that_replaced_the_images_entries_cannot_import_the_team_code() {
        let dir = tempfile::tempdir().unwrap();
        let egg = egg(dir.path(), "carla-0.9.15-py3.7-linux-x86_64.egg");
        let imports = job_env("/workspace/scenario_runner:/workspace/leaderboard", &egg);
        let failure = imports.check().unwrap_err();
        assert_eq!(
            failure.error,
            "ModuleNotFoundError: No module named 'team_code'"
        );
        assert_eq!(failure.frame.0, "__init__");
    }

    #[test]
    fn an_egg_named_other_than_the_image_has_cannot_import_carla() {
        let dir = tempfile::tempdir().unwrap();
        let present = egg(dir.path(), "carla-leaderboard-py3x.egg");
        let mut imports = job_env(
            "/workspace/scenario_runner:/workspace/leaderboard:/opt/team_code",
            &present,
        );
        imports.python_path[0] = dir
            .path()
            .join("carla-0.9.10-py3.7-linux-x86_64.egg")
            .display()
            .to_string();
        assert_eq!(
            imports.check().unwrap_err().error,
            "ModuleNotFoundError: No module named 'carla'"
        );
        // A Python 2 egg does not do either.
        let py2 = egg(dir.path(), "carla-0.9.10-py2.7-linux-x86_64.egg");
        imports.python_path[0] = py2.display().to_string();
        assert!(imports.check().is_err());
    }

    #[test]
    fn without_the_official_roots_nothing_is_required() {
        assert_eq!(Imports::default().check(), Ok(()));
    }
}
