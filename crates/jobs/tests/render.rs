//! Rendering the built-in templates for real plans: names, labels, env, images, route
//! subsets, ports, GPUs, mounts, isolation of the agent, several Jobs, hostile inputs, and
//! the golden files under `tests/golden/` (regenerate with `LB_UPDATE_GOLDEN=1`).

use std::collections::BTreeMap;
use std::path::PathBuf;

use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::{Container, PodSpec};
use lb_domain::job::plan::{plan, PlanInput, SUBMISSION_LABEL, TEAM_LABEL};
use lb_domain::results::Leaderboard;
use lb_domain::settings::{Images, LeaderboardSettings};
use lb_jobs::template::{LEADERBOARD_10, LEADERBOARD_20};
use lb_jobs::{
    render_plan, ContextError, JobContext, JobSettings, JobTemplate, RenderError, SubmissionInfo,
    TemplateError,
};
use proptest::prelude::*;
use serde_json::Value;

const CARLA_20: &str = "342236305043.dkr.ecr.us-west-2.amazonaws.com/leaderboard-20:carla-0.9.15";
const CARLA_10: &str = "342236305043.dkr.ecr.us-west-2.amazonaws.com/leaderboard-10:carla-0.9.10.1";
const PRIVATE: &str =
    "342236305043.dkr.ecr.us-west-2.amazonaws.com/leaderboard-20:private-contents";
const AGENT: &str = "342236305043.dkr.ecr.us-west-2.amazonaws.com/team-77:submission-4242";

fn settings(leaderboard: Leaderboard) -> JobSettings {
    let deployment = LeaderboardSettings {
        cluster: "leaderboard-20".into(),
        namespace: "submissions".into(),
        bucket: "leaderboard-20-results".into(),
        submissions_table: "submissions".into(),
        qualifier_table: "qualifier".into(),
        images: Images {
            carla: match leaderboard {
                Leaderboard::V1 => CARLA_10,
                Leaderboard::V2 => CARLA_20,
            }
            .into(),
            private_contents: PRIVATE.into(),
        },
        instance_type: "g5.12xlarge".into(),
        gpu_model: None,
        capacity: Default::default(),
        gpus_per_node: 4,
        tracks: BTreeMap::new(),
        qualifier: Default::default(),
        job_role_arn: String::new(),
        max_cluster_outage_hours: 6,
        max_queue_hours: 24,
        team_limit: 2,
        pair_resources: None,
        partial_update_seconds: 30,
        move_window_seconds: lb_domain::capacity::consolidation::MOVE_WINDOW_SECONDS,
        max_log_objects_per_pair: lb_domain::job::uploads::LOG_OBJECTS_PER_PAIR,
    };
    JobSettings::from_deployment(
        leaderboard,
        &deployment,
        "us-west-2",
        "arn:aws:iam::342236305043:role/leaderboard-20-submission-s3",
    )
    .unwrap()
}

fn submission(team: &str, image: &str) -> SubmissionInfo {
    SubmissionInfo {
        submission_id: 4242,
        challenge_id: 2098,
        phase_id: 4191,
        team_id: 77,
        team_name: team.into(),
        leaderboard: Leaderboard::V2,
        track: "SENSORS".into(),
        image: image.into(),
        routes: 20,
        workers: 4,
        resuming: false,
        execution: "5f0c9e3a-6b1e-4c41-9d0e-2a7d3c1b8e44".into(),
        arrived_ms: None,
        submitted_at: 0,
    }
}

fn jobs(leaderboard: Leaderboard, routes: u32, workers: u32, team: &str) -> Vec<Job> {
    let p = plan(PlanInput {
        submission_id: 4242,
        team_name: team,
        routes,
        workers,
    })
    .unwrap();
    render_plan(
        leaderboard,
        &p,
        &submission(team, AGENT),
        &settings(leaderboard),
    )
    .unwrap()
}

fn pod(job: &Job) -> &PodSpec {
    job.spec.as_ref().unwrap().template.spec.as_ref().unwrap()
}

fn container<'j>(job: &'j Job, name: &str) -> &'j Container {
    let p = pod(job);
    p.containers
        .iter()
        .chain(p.init_containers.iter().flatten())
        .find(|c| c.name == name)
        .unwrap_or_else(|| panic!("no container {name}"))
}

fn env(c: &Container) -> BTreeMap<String, String> {
    c.env
        .iter()
        .flatten()
        .map(|e| (e.name.clone(), e.value.clone().unwrap_or_default()))
        .collect()
}

fn mounts(c: &Container) -> Vec<(String, String, String)> {
    c.volume_mounts
        .iter()
        .flatten()
        .map(|m| {
            (
                m.mount_path.clone(),
                m.name.clone(),
                m.sub_path.clone().unwrap_or_default(),
            )
        })
        .collect()
}

/// A container's `nvidia.com/gpu` (request, limit).
fn gpus(c: &Container) -> Option<(String, String)> {
    let r = resources(c);
    Some((
        r.get("requests.nvidia.com/gpu")?.clone(),
        r.get("limits.nvidia.com/gpu")?.clone(),
    ))
}

fn names(job: &Job) -> Vec<String> {
    pod(job).containers.iter().map(|c| c.name.clone()).collect()
}

fn command(c: &Container) -> Vec<String> {
    c.command
        .iter()
        .flatten()
        .chain(c.args.iter().flatten())
        .cloned()
        .collect()
}

#[test]
fn a_20_route_4_worker_leaderboard_2_submission_is_four_jobs_of_one_pair() {
    let jobs = jobs(Leaderboard::V2, 20, 4, "Team Zoë");
    assert_eq!(jobs.len(), 4);
    for (i, job) in jobs.iter().enumerate() {
        let id = i + 1;
        assert_eq!(
            job.metadata.name.as_deref(),
            Some(format!("lb-4242-team-zoe-{i}").as_str())
        );
        assert_eq!(job.metadata.namespace.as_deref(), Some("submissions"));
        assert_eq!(
            names(job),
            [
                format!("simulator-{id}"),
                format!("agent-{id}"),
                "logcopy".into()
            ]
        );
        let init: Vec<&str> = pod(job)
            .init_containers
            .iter()
            .flatten()
            .map(|c| c.name.as_str())
            .collect();
        assert_eq!(init, ["private-contents"]);
        assert_eq!(env(container(job, "logcopy"))["LB_PAIRS"], id.to_string());

        // Each pair its own retry budget; pairs share nodes (no anti-affinity).
        let spec = job.spec.as_ref().unwrap();
        assert_eq!(spec.backoff_limit, Some(4));
        assert_eq!(spec.active_deadline_seconds, Some(4 * 24 * 3600));
        assert_eq!(pod(job).restart_policy.as_deref(), Some("Never"));
        // A disrupted pod is never counted; the exits no retry can change end the Job.
        assert_eq!(spec.pod_replacement_policy.as_deref(), Some("Failed"));
        let rules = &spec.pod_failure_policy.as_ref().unwrap().rules;
        assert_eq!(rules[0].action, "Ignore");
        let on = &rules[0].on_pod_conditions.as_ref().unwrap()[0];
        assert_eq!(
            (on.type_.as_str(), on.status.as_deref()),
            ("DisruptionTarget", Some("True"))
        );
        assert_eq!(rules[1].action, "FailJob");
        assert_eq!(rules[1].on_exit_codes.as_ref().unwrap().values, [3, 78]);
        assert!(!env(container(job, "logcopy")).contains_key("LB_BACKOFF_LIMIT"));
        assert_eq!(pod(job).automount_service_account_token, Some(false));
        assert_eq!(pod(job).enable_service_links, Some(false));
        assert!(pod(job).affinity.is_none(), "{:?}", pod(job).affinity);
        assert_eq!(
            pod(job).service_account_name.as_deref(),
            Some("submission-worker")
        );
        // Any node of the GPU model, Spot or on-demand (the default capacity).
        assert_eq!(
            pod(job).node_selector.as_ref().unwrap(),
            &BTreeMap::from([(
                "leaderboard.carla.org/gpu-model".to_string(),
                "nvidia-a10g".to_string()
            )])
        );
    }

    for (i, subset) in ["0-4", "5-9", "10-14", "15-19"].iter().enumerate() {
        let id = i + 1;
        let job = &jobs[i];
        for role in ["simulator", "agent"] {
            let c = container(job, &format!("{role}-{id}"));
            let e = env(c);
            assert_eq!(e["LB_SUBMISSION_ID"], "4242");
            assert_eq!(e["LB_JOB_INDEX"], i.to_string());
            assert_eq!(e["LB_LEADERBOARD"], "2.0");
            assert_eq!(e["LB_PAIR_ID"], id.to_string());
            assert_eq!(e["ROUTES_SUBSET"], *subset);
            assert_eq!(e["CARLA_PORT"], "2000");
            assert_eq!(e["CARLA_TM_PORT"], "2010");
            assert_eq!(e["REPETITIONS"], "1");
            assert_eq!(e["LB_START_WAIT_SECONDS"], "3600");
            assert_eq!(command(c)[0], "/opt/lb/lb-sidecar");
        }
        let sim = container(job, &format!("simulator-{id}"));
        assert_eq!(sim.image.as_deref(), Some(CARLA_20));
        assert_eq!(sim.working_dir.as_deref(), Some("/home/carla"));
        assert_eq!(
            command(sim)[1..],
            [
                "simulator",
                "--",
                "./CarlaUE4.sh",
                "-vulkan",
                "-carla-rpc-port={carla_port}",
                "-RenderOffScreen",
                "-nosound",
                "-ini:[/Script/Engine.RendererSettings]:r.GraphicsAdapter={gpu_index}",
            ]
        );
        // The GPU: the agent's by the device plugin, handed to CARLA by UUID.
        let e = env(sim);
        assert_eq!(e["NVIDIA_VISIBLE_DEVICES"], "all");
        assert_eq!(e["LB_GPU_FROM_AGENT"], "true");
        assert_eq!(gpus(sim), None);
        let agent = container(job, &format!("agent-{id}"));
        assert!(!env(agent).contains_key("NVIDIA_VISIBLE_DEVICES"));
        assert_eq!(gpus(agent), Some(("1".into(), "1".into())));
        assert_eq!(agent.image.as_deref(), Some(AGENT));
        let e = env(agent);
        assert_eq!(e["CHALLENGE_TRACK_CODENAME"], "SENSORS");
        assert_eq!(
            e["ROUTES"],
            "/workspace/leaderboard/data/routes_testing.xml"
        );
        assert_eq!(e["LB_MAX_IDLE_SECONDS"], "800");
        assert_eq!(e["LEADERBOARD_ROOT"], "/workspace/leaderboard");
        assert!(!e.contains_key("SCENARIOS"));
        let cmd = command(agent);
        assert_eq!(cmd[1..5], ["agent", "--", "bash", "-c"]);
        for flag in [
            "--traffic-manager-port=\"${CARLA_TM_PORT}\"",
            "--debug-checkpoint=\"${DEBUG_CHECKPOINT_ENDPOINT}\"",
            "--routes-subset=\"${ROUTES_SUBSET}\"",
            "--checkpoint=\"${CHECKPOINT_ENDPOINT}\"",
            "--resume=\"${RESUME}\"",
            "agent_sources.sh",
        ] {
            assert!(cmd[5].contains(flag), "{flag} missing from {}", cmd[5]);
        }
        assert_eq!(
            mounts(agent),
            [
                (
                    "/tmp/status".into(),
                    "logs".into(),
                    "containers-status".into()
                ),
                ("/tmp/agent".into(), "logs".into(), "agent".into()),
                ("/tmp/logs".into(), "logs".into(), "logs".into()),
                ("/opt/lb".into(), "lb-bin".into(), String::new()),
                ("/dev/shm".into(), "dshm".into(), String::new()),
                // The pair's own handoff folder; the GPU pin is the simulator's alone.
                (
                    "/tmp/handoff".into(),
                    "handoff".into(),
                    format!("pair-{id}")
                ),
                (
                    "/workspace/leaderboard".into(),
                    "leaderboard".into(),
                    String::new()
                ),
                (
                    "/workspace/scenario_runner".into(),
                    "scenario-runner".into(),
                    String::new()
                ),
                ("/workspace/CARLA".into(), "carla-api".into(), String::new()),
            ]
        );
        assert_eq!(
            mounts(sim)[..3],
            [
                (
                    "/tmp/status".into(),
                    "logs".into(),
                    "containers-status".into()
                ),
                ("/tmp/logs".into(), "logs".into(), "logs".into()),
                ("/opt/lb".into(), "lb-bin".into(), String::new()),
            ]
        );
        let handoff = (
            "/tmp/handoff".into(),
            "handoff".into(),
            format!("pair-{id}"),
        );
        assert!(mounts(sim).contains(&handoff));
        let pin = (
            "/tmp/gpu-pin".into(),
            "gpu-pin".into(),
            format!("pair-{id}"),
        );
        assert!(mounts(sim).contains(&pin));
        assert!(!mounts(agent)
            .iter()
            .any(|(_, volume, _)| volume == "gpu-pin"));
    }

    let job = &jobs[3];
    let logcopy = container(job, "logcopy");
    assert_eq!(logcopy.image.as_deref(), Some(PRIVATE));
    assert_eq!(command(logcopy), ["/opt/lb/lb-sidecar", "logcopy"]);
    let e = env(logcopy);
    assert_eq!(e["LB_PAIRS"], "4");
    assert_eq!(e["LB_S3_BUCKET"], "leaderboard-20-results");
    assert_eq!(e["LB_PERIOD_SECONDS"], "10");
    assert_eq!(e["AWS_REGION"], "us-west-2");
    assert_eq!(
        e["AWS_ROLE_ARN"],
        "arn:aws:iam::342236305043:role/leaderboard-20-submission-s3"
    );
    assert_eq!(
        e["AWS_WEB_IDENTITY_TOKEN_FILE"],
        "/var/run/secrets/eks.amazonaws.com/serviceaccount/token"
    );
    assert_eq!(
        mounts(logcopy)[0],
        ("/logs".into(), "logs".into(), String::new())
    );

    let init = container(job, "private-contents");
    assert_eq!(command(init), ["lb-sidecar", "init"]);
    let e = env(init);
    assert_eq!(e["LB_PAIRS"], "4");
    assert_eq!(e["LB_PARTICIPANT_RESUME"], "");
    assert_eq!(e["LB_SOURCE_LEADERBOARD"], "/src/leaderboard");
    assert!(e.contains_key("AWS_ROLE_ARN"));
}

#[test]
fn every_job_and_its_pods_carry_the_submission_labels() {
    let jobs = jobs(Leaderboard::V2, 20, 4, "Team Zoë");
    let job = &jobs[0];
    let labels = job.metadata.labels.as_ref().unwrap();
    let expected: BTreeMap<String, String> = [
        ("app.kubernetes.io/component", "submission"),
        ("app.kubernetes.io/managed-by", "leaderboard-cloud"),
        (
            "leaderboard.carla.org/execution",
            "5f0c9e3a-6b1e-4c41-9d0e-2a7d3c1b8e44",
        ),
        ("leaderboard.carla.org/job-index", "0"),
        ("leaderboard.carla.org/leaderboard", "2.0"),
        ("leaderboard.carla.org/submission-id", "4242"),
        ("leaderboard.carla.org/team", "Team-Zoe"),
        ("leaderboard.carla.org/team-id", "77"),
        ("leaderboard.carla.org/track", "SENSORS"),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_owned(), v.to_owned()))
    .collect();
    assert_eq!(labels, &expected);
    let template = job
        .spec
        .as_ref()
        .unwrap()
        .template
        .metadata
        .as_ref()
        .unwrap();
    assert_eq!(template.labels.as_ref(), Some(&expected));
    assert_eq!(
        template.annotations.as_ref().unwrap()["leaderboard.carla.org/team-name"],
        "Team Zoë"
    );
}

#[test]
fn the_team_name_annotation_has_no_bidirectional_zero_width_or_control_characters() {
    // U+202E turns "Team evil" into "Team live" on a terminal; U+200B hides inside a name.
    let jobs = jobs(
        Leaderboard::V2,
        20,
        4,
        "Team \u{202e}live\u{200b}\u{1b}[31m\nX",
    );
    let annotations = jobs[0].metadata.annotations.as_ref().unwrap();
    assert_eq!(annotations["leaderboard.carla.org/team-name"], "Team liveX");
}

#[test]
fn no_aws_variable_or_token_reaches_the_simulators_and_agents() {
    for leaderboard in [Leaderboard::V1, Leaderboard::V2] {
        let jobs = jobs(leaderboard, 20, 4, "t");
        let p = pod(&jobs[0]);
        for c in p.containers.iter().filter(|c| c.name != "logcopy") {
            let raw = serde_json::to_string(c).unwrap();
            assert!(!raw.contains("AWS_"), "{} has AWS variables", c.name);
            assert!(!raw.contains("token"), "{} mentions a token", c.name);
            assert!(!raw.contains("/var/run/secrets"), "{}", c.name);
            assert!(c.env_from.is_none());
            assert_ne!(
                c.security_context.as_ref().and_then(|s| s.privileged),
                Some(true)
            );
        }
        // The projected token is mounted by init and logcopy only.
        let token_users: Vec<&str> = p
            .containers
            .iter()
            .chain(p.init_containers.iter().flatten())
            .filter(|c| {
                c.volume_mounts
                    .iter()
                    .flatten()
                    .any(|m| m.name == "aws-iam-token")
            })
            .map(|c| c.name.as_str())
            .collect();
        assert_eq!(token_users, ["logcopy", "private-contents"]);
        assert_eq!(p.automount_service_account_token, Some(false));
    }
}

#[test]
fn a_12_route_3_worker_leaderboard_1_submission_runs_three_pairs_five_times() {
    let jobs = jobs(Leaderboard::V1, 12, 3, "team");
    assert_eq!(jobs.len(), 3);
    for (i, subset) in ["0-3", "4-7", "8-11"].iter().enumerate() {
        let job = &jobs[i];
        let id = i + 1;
        assert_eq!(
            names(job),
            [
                format!("simulator-{id}"),
                format!("agent-{id}"),
                "logcopy".into()
            ]
        );
        let sim = container(job, &format!("simulator-{id}"));
        assert_eq!(sim.image.as_deref(), Some(CARLA_10));
        assert_eq!(
            command(sim)[1..],
            [
                "simulator",
                "--",
                "./CarlaUE4.sh",
                "-opengl",
                "-nosound",
                "-carla-rpc-port={carla_port}"
            ]
        );
        let e = env(sim);
        assert_eq!(e["SDL_VIDEODRIVER"], "offscreen");
        // EGL picks the CUDA device: the agent's GPU, by its index in PCI order.
        assert_eq!(e["SDL_HINT_CUDA_DEVICE"], "{gpu_index}");
        assert_eq!(e["CUDA_DEVICE_ORDER"], "PCI_BUS_ID");
        assert_eq!(e["NVIDIA_VISIBLE_DEVICES"], "all");
        assert_eq!(e["LB_GPU_FROM_AGENT"], "true");
        let agent = container(job, &format!("agent-{id}"));
        assert_eq!(gpus(agent), Some(("1".into(), "1".into())));
        let e = env(agent);
        assert_eq!(e["ROUTES_SUBSET"], *subset);
        assert_eq!(e["REPETITIONS"], "5");
        assert_eq!(e["LB_LEADERBOARD"], "1.0");
        assert_eq!(
            e["SCENARIOS"],
            "/workspace/leaderboard/data/all_towns_traffic_scenarios_private.json"
        );
        let cmd = &command(agent)[5];
        assert!(cmd.contains("--scenarios=\"${SCENARIOS}\""));
        assert!(!cmd.contains("traffic-manager-port"));
        assert!(cmd.contains("--trafficManagerPort=\"${CARLA_TM_PORT}\""));
        assert!(!cmd.contains("debug-checkpoint"));
        assert!(!e.contains_key("NVIDIA_VISIBLE_DEVICES"));
        assert_eq!(env(container(job, "logcopy"))["LB_PAIRS"], id.to_string());
    }
}

/// Runs an agent container's shell script as the pod would, with `python3` a stub that prints
/// what the evaluator would see, `HOME` holding the image's dotfiles.
fn run_agent_script(job: &Job, image_python_path: Option<&str>, egg: &str) -> Vec<String> {
    let agent = container(job, "agent-1");
    let script = command(agent)[5].clone();
    let dir = tempfile::tempdir().unwrap();
    let home = dir.path().join("home");
    let carla = dir.path().join("CARLA");
    let bin = dir.path().join("bin");
    for d in [&home, &carla.join("PythonAPI/carla/dist"), &bin] {
        std::fs::create_dir_all(d).unwrap();
    }
    std::fs::write(carla.join("PythonAPI/carla/dist").join(egg), "egg").unwrap();
    std::fs::write(home.join(".bashrc"), "echo sourced:bashrc\n").unwrap();
    std::fs::write(
        home.join("agent_sources.sh"),
        "echo sourced:agent_sources\n",
    )
    .unwrap();
    let python = bin.join("python3");
    std::fs::write(&python, "#!/bin/sh\necho \"PYTHONPATH=$PYTHONPATH\"\n").unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&python, std::fs::Permissions::from_mode(0o755)).unwrap();
    let mut cmd = std::process::Command::new("bash");
    cmd.arg("-c").arg(&script).env_clear();
    // The container's env as rendered (Kubernetes sets these), then the image's own.
    for (k, v) in env(agent) {
        cmd.env(k, v);
    }
    cmd.env("CARLA_ROOT", &carla)
        .env("HOME", &home)
        .env("PATH", format!("{}:/usr/bin:/bin", bin.display()));
    if let Some(p) = image_python_path {
        cmd.env("PYTHONPATH", p);
    }
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(str::to_owned)
        .collect()
}

#[test]
fn the_agent_prepends_the_official_code_to_the_images_pythonpath_after_its_dotfiles() {
    for leaderboard in [Leaderboard::V1, Leaderboard::V2] {
        let jobs = jobs(leaderboard, 4, 1, "team");
        let agent = container(&jobs[0], "agent-1");
        assert!(
            !env(agent).contains_key("PYTHONPATH"),
            "{leaderboard}: a container PYTHONPATH would replace the image's"
        );
        let lines = run_agent_script(
            &jobs[0],
            Some("/opt/team_code:/opt/lib"),
            "carla-leaderboard-py3x.egg",
        );
        assert_eq!(lines[0], "sourced:bashrc", "{leaderboard}: {lines:?}");
        assert_eq!(
            lines[1], "sourced:agent_sources",
            "{leaderboard}: {lines:?}"
        );
        let path: Vec<&str> = lines[2]
            .strip_prefix("PYTHONPATH=")
            .unwrap()
            .split(':')
            .collect();
        assert!(
            path[0].ends_with("/PythonAPI/carla/dist/carla-leaderboard-py3x.egg"),
            "{path:?}"
        );
        assert_eq!(
            path[2..],
            [
                "/workspace/scenario_runner",
                "/workspace/leaderboard",
                "/opt/team_code",
                "/opt/lib"
            ],
            "{leaderboard}"
        );
        // An image without PYTHONPATH gets no empty entry; the egg keeps its versioned name.
        let lines = run_agent_script(&jobs[0], None, "carla-0.9.15-py3.7-linux-x86_64.egg");
        let path = lines[2].strip_prefix("PYTHONPATH=").unwrap();
        assert!(path.ends_with("/workspace/leaderboard"), "{path}");
        assert!(
            path.contains("carla-0.9.15-py3.7-linux-x86_64.egg"),
            "{path}"
        );
    }
}

#[test]
fn more_workers_than_gpus_of_a_node_are_still_one_job_each_with_global_pair_ids() {
    let jobs = jobs(Leaderboard::V2, 20, 10, "team");
    let job_names: Vec<&str> = jobs
        .iter()
        .map(|j| j.metadata.name.as_deref().unwrap())
        .collect();
    let expected: Vec<String> = (0..10).map(|i| format!("lb-4242-team-{i}")).collect();
    assert_eq!(job_names, expected);
    assert_eq!(names(&jobs[9]), ["simulator-10", "agent-10", "logcopy"]);
    let e = env(container(&jobs[9], "agent-10"));
    assert_eq!(e["LB_JOB_INDEX"], "9");
    assert_eq!(e["LB_PAIR_ID"], "10");
    assert_eq!(e["CARLA_PORT"], "2000");
    assert_eq!(e["ROUTES_SUBSET"], "18-19");
    assert_eq!(env(container(&jobs[4], "logcopy"))["LB_PAIRS"], "5");
    for (i, job) in jobs.iter().enumerate() {
        let labels = job.metadata.labels.as_ref().unwrap();
        assert_eq!(labels[SUBMISSION_LABEL], "4242");
        assert_eq!(labels["leaderboard.carla.org/job-index"], i.to_string());
    }
}

#[test]
fn a_qualifier_track_runs_the_qualifier_routes_and_a_resume_is_passed_to_init() {
    let p = plan(PlanInput {
        submission_id: 4242,
        team_name: "t",
        routes: 10,
        workers: 2,
    })
    .unwrap();
    let mut s = submission("t", AGENT);
    s.track = "SENSORS_QUALIFIER".into();
    s.resuming = true;
    let mut qualifier = settings(Leaderboard::V2);
    qualifier.qualifier = true;
    let jobs = render_plan(Leaderboard::V2, &p, &s, &qualifier).unwrap();
    let e = env(container(&jobs[0], "agent-1"));
    assert_eq!(
        e["ROUTES"],
        "/workspace/leaderboard/data/routes_qualifier.xml"
    );
    assert_eq!(e["CHALLENGE_TRACK_CODENAME"], "SENSORS_QUALIFIER");
    assert_eq!(
        env(container(&jobs[0], "private-contents"))["LB_PARTICIPANT_RESUME"],
        "1"
    );
}

#[test]
fn hostile_images_are_refused_before_rendering() {
    let p = plan(PlanInput {
        submission_id: 4242,
        team_name: "t",
        routes: 20,
        workers: 4,
    })
    .unwrap();
    for bad in [
        "",
        "img:latest\n    command: [sh]",
        "img --privileged",
        "Team/Agent:latest",
        "img:$(AWS_ROLE_ARN)",
        "img@sha256:short",
    ] {
        let err = render_plan(
            Leaderboard::V2,
            &p,
            &submission("t", bad),
            &settings(Leaderboard::V2),
        )
        .unwrap_err();
        assert_eq!(err.name(), "InvalidImage", "{bad:?}");
        assert!(
            matches!(
                &err,
                RenderError::Context(ContextError::InvalidImage {
                    field: "participant image",
                    ..
                })
            ),
            "{err}"
        );
    }
    let mut s = settings(Leaderboard::V2);
    s.carla_image = "carla image".into();
    let err = render_plan(Leaderboard::V2, &p, &submission("t", AGENT), &s).unwrap_err();
    assert!(err.to_string().contains("CARLA image"), "{err}");
}

#[test]
fn invalid_settings_are_named() {
    let p = plan(PlanInput {
        submission_id: 4242,
        team_name: "t",
        routes: 20,
        workers: 4,
    })
    .unwrap();
    type Edit = Box<dyn Fn(&mut JobSettings)>;
    let edits: Vec<(&str, Edit)> = vec![
        ("namespace", Box::new(|s| s.namespace = "Bad NS".into())),
        (
            "s3_role_arn",
            Box::new(|s| s.s3_role_arn = "arn:aws:iam::1:role/x".into()),
        ),
        ("bucket", Box::new(|s| s.bucket = "Bucket_Name".into())),
        ("region", Box::new(|s| s.region = "us west".into())),
        (
            "routes_file",
            Box::new(|s| s.routes_file = "/data/$(AWS_ROLE_ARN).xml".into()),
        ),
        ("repetitions", Box::new(|s| s.repetitions = 0)),
        (
            "node_selector",
            Box::new(|s| {
                s.node_selector.insert("x".into(), "-bad".into());
            }),
        ),
        (
            "service_account",
            Box::new(|s| s.service_account = "-sa".into()),
        ),
    ];
    for (field, edit) in edits {
        let mut s = settings(Leaderboard::V2);
        edit(&mut s);
        let err = render_plan(Leaderboard::V2, &p, &submission("t", AGENT), &s).unwrap_err();
        assert_eq!(err.name(), "InvalidJobSetting");
        assert!(
            matches!(&err, RenderError::Context(ContextError::InvalidSetting { field: f, .. }) if *f == field),
            "{field}: {err}"
        );
    }
    let mut bad_track = submission("t", AGENT);
    bad_track.track = "sensors; rm".into();
    let err = render_plan(Leaderboard::V2, &p, &bad_track, &settings(Leaderboard::V2)).unwrap_err();
    assert!(err.to_string().contains("`track`"), "{err}");
    let mut other = submission("t", AGENT);
    other.submission_id = 1;
    let err = render_plan(Leaderboard::V2, &p, &other, &settings(Leaderboard::V2)).unwrap_err();
    assert!(
        err.to_string().contains("the plan is for submission 4242"),
        "{err}"
    );
}

fn hostile_name() -> impl Strategy<Value = String> {
    prop_oneof![
        Just(String::new()),
        Just("🚗🏎️ Fast & Furious".to_owned()),
        Just("x".repeat(300)),
        Just("'; DROP TABLE teams; --".to_owned()),
        Just("team\nkind: Pod\n  evil: true".to_owned()),
        Just("{{ .Values }} $(AWS_ROLE_ARN) ${HOME}".to_owned()),
        Just("\u{1b}[31mred\u{1b}[0m\u{0}".to_owned()),
        Just("-._-".to_owned()),
        ".{0,200}",
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn any_team_name_renders_valid_jobs_with_label_safe_values(name in hostile_name()) {
        let jobs = jobs(Leaderboard::V2, 20, 2, &name);
        prop_assert_eq!(jobs.len(), 2);
        for job in &jobs {
            let n = job.metadata.name.as_deref().unwrap();
            prop_assert!(lb_domain::job::plan::is_dns_label(n), "{}", n);
            let label = &job.metadata.labels.as_ref().unwrap()[TEAM_LABEL];
            prop_assert!(lb_domain::job::plan::is_label_value(label), "{:?}", label);
            let annotation = &job.metadata.annotations.as_ref().unwrap()["leaderboard.carla.org/team-name"];
            prop_assert!(!annotation.chars().any(char::is_control));
            prop_assert!(annotation.chars().count() <= 256);
        }
        prop_assert_ne!(jobs[0].metadata.name.as_ref(), jobs[1].metadata.name.as_ref());
    }
}

#[test]
fn every_dollar_path_in_the_templates_resolves_against_the_job_context() {
    for leaderboard in [Leaderboard::V1, Leaderboard::V2] {
        let template = JobTemplate::builtin(leaderboard).unwrap();
        let ctx = JobContext::sample(leaderboard);
        let mut input = serde_json::to_value(&ctx).unwrap();
        input["pair"] = serde_json::to_value(&ctx.pairs[0]).unwrap();
        input["assembled"] = serde_json::json!({"init_containers": [], "containers": []});
        let fields = template.dynamic_fields();
        assert!(fields.len() > 30, "{}", fields.len());
        for (section, field) in fields {
            for path in field.paths {
                assert!(
                    path.select(&input, &Value::Null).is_some(),
                    "{}: {section} {} reads {} which the context lacks",
                    template.name(),
                    field.location,
                    path.text()
                );
            }
        }
    }
}

#[test]
fn a_template_reading_a_missing_context_key_fails_to_load() {
    let broken = LEADERBOARD_20.replace("$.images.carla", "$.images.carla_typo");
    let err = JobTemplate::parse("broken", &broken).unwrap_err();
    assert!(matches!(err, TemplateError::Check { .. }), "{err:?}");
    let msg = err.to_string();
    assert!(msg.contains("'$.images.carla_typo'"), "{msg}");
    assert!(msg.contains("States.Runtime"), "{msg}");
    assert_eq!(RenderError::from(err).name(), "InvalidJobTemplate");
}

#[test]
fn a_misplaced_or_unknown_kubernetes_field_fails_to_load_with_its_path() {
    let broken = LEADERBOARD_10.replace("    workingDir: /home/carla", "    workDir: /home/carla");
    let msg = JobTemplate::parse("broken", &broken)
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("`spec.template.spec.containers[0].workDir`"),
        "{msg}"
    );
    let broken = LEADERBOARD_20.replace(
        "        restartPolicy: Never",
        "        restartPolicy: OnFailure",
    );
    let msg = JobTemplate::parse("broken", &broken)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("restartPolicy"), "{msg}");
}

/// A container's resources as (kind, name) -> quantity.
fn resources(c: &Container) -> BTreeMap<String, String> {
    let r = c.resources.as_ref().unwrap();
    [("requests", &r.requests), ("limits", &r.limits)]
        .into_iter()
        .flat_map(|(kind, map)| {
            map.iter()
                .flatten()
                .map(move |(k, v)| (format!("{kind}.{k}"), v.0.clone()))
        })
        .collect()
}

#[test]
fn every_container_is_confined_and_sized_from_the_settings() {
    for (leaderboard, workers) in [(Leaderboard::V2, 6), (Leaderboard::V1, 3)] {
        for job in jobs(leaderboard, 20, workers, "team") {
            let pod = pod(&job);
            let pod_seccomp = pod
                .security_context
                .as_ref()
                .unwrap()
                .seccomp_profile
                .as_ref();
            assert_eq!(pod_seccomp.unwrap().type_, "RuntimeDefault");
            let pairs = (pod.containers.len() as u32 - 1) / 2;
            let shm = pod
                .volumes
                .iter()
                .flatten()
                .find(|v| v.name == "dshm")
                .unwrap();
            let dir = shm.empty_dir.as_ref().unwrap();
            assert_eq!(dir.medium.as_deref(), Some("Memory"));
            // g5.12xlarge, 4 pairs a node: 6 GiB of /dev/shm per pair.
            assert_eq!(
                dir.size_limit.as_ref().unwrap().0,
                format!("{}Mi", 6144 * pairs)
            );
            for c in pod
                .containers
                .iter()
                .chain(pod.init_containers.iter().flatten())
            {
                let sc = c.security_context.as_ref().unwrap();
                assert_eq!(sc.allow_privilege_escalation, Some(false), "{}", c.name);
                assert_eq!(sc.privileged, None, "{}", c.name);
                let caps = sc.capabilities.as_ref().unwrap();
                assert_eq!(caps.drop.as_deref(), Some(&["ALL".to_string()][..]));
                assert_eq!(caps.add, None);
                let agent = c.name.starts_with("agent-");
                // Participants' images run as root; everything else is CARLA's user.
                assert_eq!(sc.run_as_non_root, (!agent).then_some(true), "{}", c.name);
                assert_eq!(sc.run_as_user, (!agent).then_some(1000), "{}", c.name);
                // Disk: a request for what it normally writes, a limit where the kubelet
                // evicts it as a failure of its own; logcopy's also holds the room of every
                // disk-backed volume, so a pod within its limits is within its request.
                let logcopy = format!("{}Gi", 1 + disk_volumes_gib(pod));
                let (cpu, memory, disk, disk_limit) = match c.name.split('-').next().unwrap() {
                    "simulator" => ("4000m", "16384Mi", "1Gi", "4Gi"),
                    "agent" => ("6000m", "24576Mi", "4Gi", "16Gi"),
                    "logcopy" => ("500m", "512Mi", logcopy.as_str(), logcopy.as_str()),
                    _ => ("500m", "512Mi", "1Gi", "1Gi"),
                };
                let mut expected: BTreeMap<String, String> = [
                    ("limits.cpu", cpu),
                    ("limits.memory", memory),
                    ("limits.ephemeral-storage", disk_limit),
                    ("requests.cpu", cpu),
                    ("requests.memory", memory),
                    ("requests.ephemeral-storage", disk),
                ]
                .into_iter()
                .map(|(k, v)| (k.to_owned(), v.to_owned()))
                .collect();
                if agent {
                    // The pair's one GPU is the agent's.
                    for k in ["limits.nvidia.com/gpu", "requests.nvidia.com/gpu"] {
                        expected.insert(k.to_owned(), "1".to_owned());
                    }
                }
                assert_eq!(resources(c), expected, "{}", c.name);
            }
        }
    }
}

/// The `sizeLimit`s of the pod's disk-backed `emptyDir`s together, GiB rounded up.
fn disk_volumes_gib(pod: &PodSpec) -> u64 {
    let mib: u64 = pod
        .volumes
        .iter()
        .flatten()
        .filter_map(|v| v.empty_dir.as_ref())
        .filter(|d| d.medium.as_deref() != Some("Memory"))
        .map(|d| {
            let q = &d.size_limit.as_ref().expect("every emptyDir is bounded").0;
            match q.split_at(q.len() - 2) {
                (n, "Gi") => n.parse::<u64>().unwrap() * 1024,
                (n, "Mi") => n.parse::<u64>().unwrap(),
                _ => panic!("unexpected quantity {q}"),
            }
        })
        .sum();
    mib.div_ceil(1024)
}

#[test]
fn every_volume_of_the_rendered_jobs_is_bounded_and_every_container_limits_its_disk() {
    for (leaderboard, workers) in [(Leaderboard::V2, 6), (Leaderboard::V1, 3)] {
        for job in jobs(leaderboard, 20, workers, "team") {
            let pod = pod(&job);
            let pairs = (pod.containers.len() as u32 - 1) / 2;
            let sizes: BTreeMap<&str, &str> = pod
                .volumes
                .iter()
                .flatten()
                .filter_map(|v| {
                    let dir = v.empty_dir.as_ref()?;
                    Some((
                        v.name.as_str(),
                        dir.size_limit.as_ref().map_or("none", |q| q.0.as_str()),
                    ))
                })
                .collect();
            let logs = format!("{}Gi", 8 * pairs);
            let expected = BTreeMap::from([
                ("logs", logs.as_str()),
                ("lb-bin", "256Mi"),
                ("leaderboard", "2048Mi"),
                ("scenario-runner", "2048Mi"),
                ("carla-api", "2048Mi"),
                ("dshm", sizes["dshm"]),
                ("handoff", "1Mi"),
                ("gpu-pin", "1Mi"),
            ]);
            assert_eq!(
                sizes,
                expected,
                "{}",
                job.metadata.name.as_deref().unwrap_or("")
            );
            for c in pod.init_containers.iter().flatten().chain(&pod.containers) {
                let r = resources(c);
                for kind in ["requests", "limits"] {
                    let disk = &r[&format!("{kind}.ephemeral-storage")];
                    assert!(disk.ends_with("Gi"), "{} {kind}: {disk}", c.name);
                }
            }
        }
    }
}

#[test]
fn only_a_pair_s_simulator_mounts_its_recordings_folder_where_the_evaluator_points_carla() {
    use lb_domain::job::protocol::{recorder_dir, RECORDER_DIR, SIMULATOR_RECORDER_MOUNT};
    for (leaderboard, workers) in [(Leaderboard::V2, 6), (Leaderboard::V1, 3)] {
        for job in jobs(leaderboard, 20, workers, "team") {
            let pod = pod(&job);
            for c in pod.init_containers.iter().flatten().chain(&pod.containers) {
                let logs_mounts: Vec<(&str, &str)> = (c.volume_mounts.iter().flatten())
                    .filter(|m| m.name == "logs")
                    .map(|m| (m.mount_path.as_str(), m.sub_path.as_deref().unwrap_or("")))
                    .collect();
                let recorder: Vec<&(&str, &str)> = logs_mounts
                    .iter()
                    .filter(|(_, sub)| sub.starts_with(RECORDER_DIR))
                    .collect();
                let role = c.name.split_once('-').map(|(role, _)| role);
                match (role, c.name.rsplit_once('-')) {
                    (Some("simulator"), Some((_, pair))) => {
                        let pair: u32 = pair.parse().unwrap();
                        let own = recorder_dir(pair);
                        assert_eq!(
                            recorder,
                            [&(SIMULATOR_RECORDER_MOUNT, own.as_str())],
                            "{}",
                            c.name
                        );
                    }
                    // Ours, reading the whole volume to upload it.
                    _ if ["logcopy", "private-contents"].contains(&c.name.as_str()) => {}
                    // The participant's container: only its own subfolders, never the root.
                    _ => {
                        assert!(recorder.is_empty(), "{}: {logs_mounts:?}", c.name);
                        assert!(
                            logs_mounts.iter().all(|(_, sub)| !sub.is_empty()),
                            "{}: {logs_mounts:?}",
                            c.name
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn an_operators_pair_resources_reach_the_containers() {
    let mut s = settings(Leaderboard::V2);
    s.resources = lb_domain::cluster::resources::PairShare {
        simulator: lb_domain::cluster::resources::ContainerShare {
            cpu: 3.5,
            memory_gib: 12.0,
        },
        agent: lb_domain::cluster::resources::ContainerShare {
            cpu: 7.0,
            memory_gib: 30.5,
        },
        shm_gib: 2.0,
    }
    .allotment();
    let p = plan(PlanInput {
        submission_id: 4242,
        team_name: "team",
        routes: 20,
        workers: 2,
    })
    .unwrap();
    let job = render_plan(Leaderboard::V2, &p, &submission("team", AGENT), &s)
        .unwrap()
        .remove(0);
    assert_eq!(
        resources(container(&job, "simulator-1"))["limits.cpu"],
        "3500m"
    );
    assert_eq!(
        resources(container(&job, "agent-1"))["requests.memory"],
        "31232Mi"
    );
    let shm = pod(&job)
        .volumes
        .iter()
        .flatten()
        .find(|v| v.name == "dshm")
        .unwrap();
    assert_eq!(
        shm.empty_dir
            .as_ref()
            .unwrap()
            .size_limit
            .as_ref()
            .unwrap()
            .0,
        "2048Mi"
    );
}

#[test]
fn a_template_that_loosens_the_confinement_does_not_load() {
    const AGENT_CAPS: &str =
        "    # Root, as participants' images expect, but without a single capability.
    securityContext:
      allowPrivilegeEscalation: false
      capabilities: {drop: [ALL]}";
    let cases: [(&str, &str, &str); 16] = [
        (AGENT_CAPS, "    securityContext:\n      allowPrivilegeEscalation: false", "containers[1].securityContext.capabilities.drop"),
        ("capabilities: {drop: [ALL]}\n    resources.$: $.resources.agent", "capabilities: {drop: [ALL], add: [NET_RAW]}\n    resources.$: $.resources.agent", "containers[1].securityContext.capabilities.add"),
        ("      runAsNonRoot: true\n", "      runAsNonRoot: false\n", ".securityContext.runAsNonRoot"),
        ("      runAsUser: 1000\n", "      runAsUser: 0\n", ".securityContext.runAsUser"),
        ("      allowPrivilegeEscalation: false\n      capabilities: {drop: [ALL]}\n    resources.$: $.resources.simulator", "      allowPrivilegeEscalation: true\n      capabilities: {drop: [ALL]}\n    resources.$: $.resources.simulator", ".securityContext.allowPrivilegeEscalation"),
        ("      capabilities: {drop: [ALL]}\n    resources.$: $.resources.agent", "      capabilities: {drop: [ALL]}\n      privileged: true\n    resources.$: $.resources.agent", "containers[1].securityContext.privileged"),
        ("seccompProfile: {type: RuntimeDefault}", "seccompProfile: {type: Unconfined}", "spec.template.spec.securityContext.seccompProfile.type"),
        (", sizeLimit.$: $.resources.shm", "", "volumes[5].emptyDir.sizeLimit"),
        ("resources.$: $.resources.agent", "resources: {limits: {cpu: '64', memory: 512Gi}}", "containers[1].resources.requests.cpu"),
        ("resources.$: $.resources.agent", "resources.$: $.resources.simulator", "containers[1].resources.requests.cpu"),
        ("        automountServiceAccountToken: false\n", "        automountServiceAccountToken: false\n        hostPID: true\n", "spec.template.spec.hostPID"),
        ("          - {name: logs, emptyDir: {sizeLimit.$: $.resources.volumes.logs}}", "          - {name: logs, hostPath: {path: /var/log}}", "volumes[0].hostPath"),
        ("{name: carla-api, emptyDir: {sizeLimit.$: $.resources.volumes.sources}}", "{name: carla-api, emptyDir: {}}", "volumes[4].emptyDir.sizeLimit"),
        ("resources.$: $.resources.agent", "resources: {limits: {cpu: 6000m, memory: 24576Mi, nvidia.com/gpu: '1'}, requests: {cpu: 6000m, memory: 24576Mi, nvidia.com/gpu: '1'}}", "containers[1].resources.requests.ephemeral-storage"),
        // The participant's container reaching the recordings: the whole volume, or the folder.
        ("      - {name: logs, mountPath: /tmp/agent, subPath: agent}", "      - {name: logs, mountPath: /tmp/agent}", "containers[1].volumeMounts[1].subPath"),
        ("      - {name: logs, mountPath: /tmp/recorder, subPath.$: \"States.Format('recorder/pair{}', $.pair.id)\"}\n", "", "containers[0].volumeMounts"),
    ];
    for (from, to, path) in cases {
        for template in [LEADERBOARD_20, LEADERBOARD_10] {
            assert!(template.contains(from), "{from:?} is not in the template");
            let msg = JobTemplate::parse("loosened", &template.replacen(from, to, 1))
                .unwrap_err()
                .to_string();
            assert!(msg.contains(path), "{to:?}: expected `{path}` in {msg}");
        }
    }
}

#[test]
fn malformed_template_files_are_refused() {
    for (text, needle) in [
        ("pair: [\n", "not a valid template file"),
        ("pair: []\nper_job: {init_containers: [], containers: []}\njob: {}\nextra: 1\n", "unknown field `extra`"),
        ("pair: [{name.$: 3}]\nper_job: {init_containers: [], containers: []}\njob: {}\n", "section `pair`"),
        (
            "pair: [{name.$: \"States.Format('{} {}', $.pair.id)\"}]\nper_job: {init_containers: [], containers: []}\njob: {}\n",
            "2 `{}` but 1 value",
        ),
    ] {
        let msg = JobTemplate::parse("t", text).unwrap_err().to_string();
        assert!(msg.contains(needle), "{text}: {msg}");
    }
}

fn golden_path(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name)
}

fn to_yaml(jobs: &[Job]) -> String {
    let mut out = String::from(
        "# Generated by crates/jobs/tests/render.rs; regenerate with LB_UPDATE_GOLDEN=1 cargo test -p lb-jobs.\n",
    );
    for job in jobs {
        out.push_str("---\n");
        out.push_str(&serde_yaml::to_string(job).unwrap());
    }
    out
}

fn check_golden(name: &str, jobs: &[Job]) {
    let path = golden_path(name);
    let rendered = to_yaml(jobs);
    if std::env::var_os("LB_UPDATE_GOLDEN").is_some() {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, &rendered).unwrap();
        return;
    }
    let expected = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("{}: {e} (run with LB_UPDATE_GOLDEN=1)", path.display()));
    assert!(
        expected == rendered,
        "{} is stale; run `LB_UPDATE_GOLDEN=1 cargo test -p lb-jobs` and review the diff",
        path.display()
    );
}

#[test]
fn the_golden_files_match_the_rendered_jobs() {
    check_golden(
        "leaderboard-20.yaml",
        &jobs(Leaderboard::V2, 20, 4, "Team Zoë"),
    );
    check_golden(
        "leaderboard-10.yaml",
        &jobs(Leaderboard::V1, 12, 3, "Team Zoë"),
    );
}

/// The cluster's Kubernetes version: `KubernetesVersion`'s default in `infra/cluster.yaml`.
fn cluster_version(root: &std::path::Path) -> String {
    let text = std::fs::read_to_string(root.join("infra/cluster.yaml")).unwrap();
    let after = text.split_once("\n  KubernetesVersion:").unwrap().1;
    let default = after.split_once("Default:").unwrap().1;
    let version = default
        .lines()
        .next()
        .unwrap()
        .trim()
        .trim_matches(['"', '\'']);
    format!("{version}.0")
}

/// Runs the pinned `kubernetes-validate` (tests/requirements.txt) on every rendered template.
#[test]
#[ignore = "needs venv"]
fn kubernetes_validate_accepts_every_rendered_job() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let tool = root.join(".venv/bin/kubernetes-validate");
    assert!(
        tool.exists(),
        "{} is missing: run `make venv`",
        tool.display()
    );
    let dir = tempfile::tempdir().unwrap();
    let mut files = Vec::new();
    for (name, jobs) in [
        ("lb20.yaml", jobs(Leaderboard::V2, 20, 10, "Team Zoë")),
        ("lb10.yaml", jobs(Leaderboard::V1, 12, 3, "team")),
    ] {
        let path = dir.path().join(name);
        std::fs::write(&path, to_yaml(&jobs)).unwrap();
        files.push(path);
    }
    let output = std::process::Command::new(&tool)
        .args([
            "--strict",
            "--quiet",
            "--kubernetes-version",
            &cluster_version(&root),
        ])
        .args(&files)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "kubernetes-validate failed:\n{}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
}
