//! A container's environment and argv: base variables, the image's ENV and PATH additions, the
//! container's `env` (values, `$(VAR)` references, `fieldRef`) and command resolution.

use std::collections::BTreeMap;

use k8s_openapi::api::core::v1::{Container, EnvVar, Pod};

use super::expand::expand;
use crate::imagemap::ImageEntry;

/// The IP this "node" and its pods report.
pub const LOCAL_IP: &str = "127.0.0.1";

/// Why a container cannot be configured (shown as `CreateContainerConfigError`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConfigError(pub String);

fn subscript<'a>(path: &'a str, prefix: &str) -> Option<&'a str> {
    let rest = path
        .strip_prefix(prefix)?
        .strip_prefix('[')?
        .strip_suffix(']')?;
    rest.strip_prefix('\'')
        .and_then(|r| r.strip_suffix('\''))
        .or_else(|| rest.strip_prefix('"').and_then(|r| r.strip_suffix('"')))
}

fn downward(path: &str, pod: &Pod) -> Option<String> {
    let meta = &pod.metadata;
    let spec = pod.spec.as_ref();
    let v = match path {
        "metadata.name" => meta.name.clone().unwrap_or_default(),
        "metadata.namespace" => meta.namespace.clone().unwrap_or_default(),
        "metadata.uid" => meta.uid.clone().unwrap_or_default(),
        "spec.nodeName" => spec.and_then(|s| s.node_name.clone()).unwrap_or_default(),
        "spec.serviceAccountName" => spec
            .and_then(|s| s.service_account_name.clone())
            .unwrap_or_default(),
        "status.hostIP" | "status.hostIPs" | "status.podIP" | "status.podIPs" => LOCAL_IP.into(),
        _ => {
            if let Some(k) = subscript(path, "metadata.labels") {
                meta.labels
                    .as_ref()
                    .and_then(|l| l.get(k))
                    .cloned()
                    .unwrap_or_default()
            } else if let Some(k) = subscript(path, "metadata.annotations") {
                meta.annotations
                    .as_ref()
                    .and_then(|a| a.get(k))
                    .cloned()
                    .unwrap_or_default()
            } else {
                return None;
            }
        }
    };
    Some(v)
}

fn value_of(
    var: &EnvVar,
    container: &str,
    pod: &Pod,
    defined: &BTreeMap<String, String>,
) -> Result<String, ConfigError> {
    if let Some(from) = &var.value_from {
        if let Some(f) = &from.field_ref {
            return downward(&f.field_path, pod).ok_or_else(|| {
                ConfigError(format!(
                    "env {:?} of container {container:?}: fieldRef {:?} is not supported",
                    var.name, f.field_path
                ))
            });
        }
        let kind = if from.secret_key_ref.is_some() {
            "secretKeyRef"
        } else if from.config_map_key_ref.is_some() {
            "configMapKeyRef"
        } else if from.resource_field_ref.is_some() {
            "resourceFieldRef"
        } else {
            "this valueFrom source"
        };
        return Err(ConfigError(format!(
            "env {:?} of container {container:?}: local-kube does not implement valueFrom.{kind}",
            var.name
        )));
    }
    let raw = var.value.clone().unwrap_or_default();
    Ok(expand(&raw, |n| defined.get(n).cloned()))
}

/// Inputs that do not come from the container spec.
pub struct EnvBase<'a> {
    /// Host `PATH` (the default before image additions).
    pub path: &'a str,
    /// Host `HOME`.
    pub home: &'a str,
}

/// The full environment of a container: base, image ENV (+ `path` dirs), container env.
pub fn environment(
    c: &Container,
    image: Option<&ImageEntry>,
    pod: &Pod,
    base: &EnvBase<'_>,
) -> Result<BTreeMap<String, String>, ConfigError> {
    if c.env_from.as_ref().is_some_and(|e| !e.is_empty()) {
        return Err(ConfigError(format!(
            "container {:?}: local-kube does not implement envFrom",
            c.name
        )));
    }
    let mut env = BTreeMap::new();
    env.insert("PATH".to_owned(), base.path.to_owned());
    env.insert("HOME".to_owned(), base.home.to_owned());
    env.insert(
        "HOSTNAME".to_owned(),
        pod.metadata.name.clone().unwrap_or_default(),
    );
    if let Some(img) = image {
        env.extend(img.env.clone());
        if !img.path.is_empty() {
            let mut parts: Vec<String> = img.path.iter().map(|p| p.display().to_string()).collect();
            parts.push(env.get("PATH").cloned().unwrap_or_default());
            env.insert("PATH".to_owned(), parts.join(":"));
        }
    }
    // NB: a container env value may only reference variables defined before it.
    let mut defined = BTreeMap::new();
    for var in c.env.iter().flatten() {
        let v = value_of(var, &c.name, pod, &defined)?;
        defined.insert(var.name.clone(), v);
    }
    env.extend(defined);
    Ok(env)
}

/// How the argv could not be formed: like an image that cannot be pulled.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NoCommand(pub String);

/// The argv: container `command` (+ `args`), else the image's command (+ container `args`, else
/// the image's `args`), else the container `args` alone; `$(VAR)` expanded with the container's
/// environment.
pub fn argv(
    c: &Container,
    image_name: &str,
    image: Option<&ImageEntry>,
    env: &BTreeMap<String, String>,
) -> Result<Vec<String>, NoCommand> {
    let command = c.command.clone().filter(|v| !v.is_empty());
    let args = c.args.clone();
    let raw: Vec<String> = match (command, image) {
        (Some(cmd), _) => cmd.into_iter().chain(args.unwrap_or_default()).collect(),
        (None, Some(entry)) if entry.command.is_some() => entry
            .command
            .clone()
            .unwrap_or_default()
            .into_iter()
            .chain(args.or_else(|| entry.args.clone()).unwrap_or_default())
            .collect(),
        (None, Some(entry)) => args.or_else(|| entry.args.clone()).unwrap_or_default(),
        (None, None) => args.unwrap_or_default(),
    };
    if raw.is_empty() || raw[0].is_empty() {
        let why = if image.is_some() {
            format!("image {image_name:?} has no command in the image map and container {:?} gives none", c.name)
        } else {
            format!(
                "image {image_name:?} is not in the image map and container {:?} has no command",
                c.name
            )
        };
        return Err(NoCommand(why));
    }
    Ok(raw
        .iter()
        .map(|a| expand(a, |n| env.get(n).cloned()))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pod() -> Pod {
        serde_yaml::from_str(
            "metadata: {name: p-abcde, namespace: ns, uid: u1, labels: {lb/submission: '42'}}\nspec: {nodeName: local-kube, containers: []}",
        )
        .unwrap()
    }

    fn container(yaml: &str) -> Container {
        serde_yaml::from_str(yaml).unwrap()
    }

    const BASE: EnvBase<'static> = EnvBase {
        path: "/usr/bin:/bin",
        home: "/root",
    };

    #[test]
    fn env_resolves_field_refs_and_earlier_variables() {
        let c = container(
            r#"
name: c
env:
- {name: POD, valueFrom: {fieldRef: {fieldPath: metadata.name}}}
- {name: NS, valueFrom: {fieldRef: {fieldPath: metadata.namespace}}}
- {name: SUB, valueFrom: {fieldRef: {fieldPath: "metadata.labels['lb/submission']"}}}
- {name: NODE, valueFrom: {fieldRef: {fieldPath: spec.nodeName}}}
- {name: IP, valueFrom: {fieldRef: {fieldPath: status.podIP}}}
- {name: PORT, value: "2000"}
- {name: TM, value: "$(PORT)0 $(LATER) $$(PORT)"}
- {name: LATER, value: x}
"#,
        );
        let env = environment(&c, None, &pod(), &BASE).unwrap();
        assert_eq!(env["POD"], "p-abcde");
        assert_eq!(env["NS"], "ns");
        assert_eq!(env["SUB"], "42");
        assert_eq!(env["NODE"], "local-kube");
        assert_eq!(env["IP"], "127.0.0.1");
        assert_eq!(env["TM"], "20000 $(LATER) $(PORT)");
        assert_eq!(env["HOSTNAME"], "p-abcde");
    }

    #[test]
    fn image_env_sits_under_the_container_env_and_path_dirs_go_first() {
        let img = ImageEntry {
            env: [("A".into(), "image".into()), ("B".into(), "image".into())].into(),
            path: vec!["/opt/fake/bin".into()],
            ..Default::default()
        };
        let c = container("{name: c, env: [{name: B, value: container}]}");
        let env = environment(&c, Some(&img), &pod(), &BASE).unwrap();
        assert_eq!(env["A"], "image");
        assert_eq!(env["B"], "container");
        assert_eq!(env["PATH"], "/opt/fake/bin:/usr/bin:/bin");
    }

    #[test]
    fn secrets_are_a_clear_configuration_error() {
        let c =
            container("{name: c, env: [{name: S, valueFrom: {secretKeyRef: {name: s, key: k}}}]}");
        let e = environment(&c, None, &pod(), &BASE).unwrap_err();
        assert!(
            e.0.contains("secretKeyRef") && e.0.contains("\"S\""),
            "{e:?}"
        );
    }

    #[test]
    fn argv_follows_docker_entrypoint_rules_and_expands() {
        let env: BTreeMap<String, String> = [("PORT".to_owned(), "2000".to_owned())].into();
        let img = ImageEntry {
            command: Some(vec!["/entry".into()]),
            args: Some(vec!["default".into()]),
            ..Default::default()
        };
        let own = container("{name: c, command: [sh, -c], args: ['echo $(PORT)']}");
        assert_eq!(
            argv(&own, "i", Some(&img), &env).unwrap(),
            ["sh", "-c", "echo 2000"]
        );
        let args_only = container("{name: c, args: [-p, $(PORT)]}");
        assert_eq!(
            argv(&args_only, "i", Some(&img), &env).unwrap(),
            ["/entry", "-p", "2000"]
        );
        let nothing = container("{name: c}");
        assert_eq!(
            argv(&nothing, "i", Some(&img), &env).unwrap(),
            ["/entry", "default"]
        );
        let e = argv(&nothing, "carla:1", None, &env).unwrap_err();
        assert!(e.0.contains("\"carla:1\" is not in the image map"), "{e:?}");
        assert_eq!(argv(&args_only, "x", None, &env).unwrap(), ["-p", "2000"]);
    }
}
