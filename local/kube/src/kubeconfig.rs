//! The kubeconfig that points kubectl and kube-rs at this server.

use serde_json::json;

/// Cluster, context and user name in the kubeconfig.
pub const CONTEXT: &str = "local-kube";

/// A kubeconfig with one cluster, user and context (namespace `default`); the bearer token is
/// included when the server requires one.
pub fn kubeconfig_yaml(server: &str, token: Option<&str>) -> String {
    let user = match token {
        Some(t) => json!({ "token": t }),
        None => json!({}),
    };
    let doc = json!({
        "apiVersion": "v1",
        "kind": "Config",
        "clusters": [{ "name": CONTEXT, "cluster": { "server": server } }],
        "users": [{ "name": CONTEXT, "user": user }],
        "contexts": [{
            "name": CONTEXT,
            "context": { "cluster": CONTEXT, "user": CONTEXT, "namespace": "default" }
        }],
        "current-context": CONTEXT,
        "preferences": {},
    });
    // NB: serializing a JSON value to YAML cannot fail.
    serde_yaml::to_string(&doc).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_kubeconfig_names_server_context_and_token() {
        let y = kubeconfig_yaml("http://127.0.0.1:1234", Some("s3cr3t"));
        let v: serde_yaml::Value = serde_yaml::from_str(&y).unwrap();
        assert_eq!(v["current-context"].as_str(), Some(CONTEXT));
        assert_eq!(
            v["clusters"][0]["cluster"]["server"].as_str(),
            Some("http://127.0.0.1:1234")
        );
        assert_eq!(v["users"][0]["user"]["token"].as_str(), Some("s3cr3t"));
        assert_eq!(
            v["contexts"][0]["context"]["namespace"].as_str(),
            Some("default")
        );
        let open = kubeconfig_yaml("http://x", None);
        assert!(!open.contains("token"));
    }
}
