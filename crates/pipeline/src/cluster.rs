//! Reaching a leaderboard's Job cluster: EKS (endpoint and CA from `DescribeCluster`, the IAM
//! token refreshed before expiry) or a kubeconfig (local mode, the local Kubernetes API).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;

use aws_config::SdkConfig;
use lb_aws::eks::{ClusterAccess, TokenSource};
use lb_cluster::Cluster;
use lb_domain::settings::LeaderboardSettings;
use tokio::sync::Mutex;

use crate::FnError;

/// How the functions reach the Job clusters.
#[derive(Debug)]
pub enum Clusters {
    /// EKS, by cluster name; access cached per cold start.
    Eks {
        /// SDK configuration (region, credentials).
        sdk: Box<SdkConfig>,
        /// Endpoint, CA, token source and client per cluster name.
        cache: Mutex<HashMap<String, EksAccess>>,
    },
    /// One kubeconfig for every leaderboard (`LB_KUBECONFIG`).
    Kubeconfig {
        /// The kubeconfig.
        path: PathBuf,
        /// Its client, built at the first use.
        client: Mutex<Option<Cluster>>,
    },
}

/// One EKS cluster's access, and the client built with the token it holds (a new token, once
/// the old one nears its expiry, builds a new client).
pub struct EksAccess {
    access: ClusterAccess,
    tokens: Arc<TokenSource>,
    client: Option<(String, Cluster)>,
}

impl std::fmt::Debug for EksAccess {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // NB: never the token the client was built with.
        f.debug_struct("EksAccess")
            .field("endpoint", &self.access.endpoint)
            .field("client", &self.client.as_ref().map(|(_, c)| c))
            .finish_non_exhaustive()
    }
}

impl Clusters {
    /// `LB_KUBECONFIG` when set (local mode), else EKS.
    pub fn from_env(sdk: &SdkConfig) -> Clusters {
        match std::env::var_os("LB_KUBECONFIG") {
            Some(path) if !path.is_empty() => Clusters::kubeconfig(PathBuf::from(path)),
            _ => Clusters::eks(sdk),
        }
    }

    /// The cluster of a kubeconfig (local mode, tests).
    pub fn kubeconfig(path: PathBuf) -> Clusters {
        Clusters::Kubeconfig {
            path,
            client: Mutex::new(None),
        }
    }

    /// EKS access through `sdk`.
    pub fn eks(sdk: &SdkConfig) -> Clusters {
        Clusters::Eks {
            sdk: Box::new(sdk.clone()),
            cache: Mutex::new(HashMap::new()),
        }
    }

    /// A client for `deployment`'s cluster, in its namespace. The client (its TLS roots, its
    /// connection pool) is built once per cold start and kept while its token is good.
    pub async fn connect(&self, deployment: &LeaderboardSettings) -> Result<Cluster, FnError> {
        let cluster = match self {
            Clusters::Kubeconfig { path, client } => {
                let mut client = client.lock().await;
                match &*client {
                    Some(cluster) => cluster.clone(),
                    None => client
                        .insert(Cluster::from_kubeconfig(path, None).await?)
                        .clone(),
                }
            }
            Clusters::Eks { sdk, cache } => {
                let mut cache = cache.lock().await;
                let eks = match cache.entry(deployment.cluster.clone()) {
                    std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
                    std::collections::hash_map::Entry::Vacant(e) => {
                        e.insert(Self::access(sdk, deployment).await?)
                    }
                };
                let token = eks.tokens.token().await?;
                match &eks.client {
                    Some((built_with, cluster)) if *built_with == token => cluster.clone(),
                    _ => {
                        let access = &eks.access;
                        let cluster = Cluster::for_eks(&access.endpoint, &access.ca_pem, &token)?;
                        eks.client = Some((token, cluster.clone()));
                        cluster
                    }
                }
            }
        };
        Ok(cluster.with_namespace(&deployment.namespace))
    }

    /// A cluster's endpoint and CA (`DescribeCluster`) and its token source.
    async fn access(
        sdk: &SdkConfig,
        deployment: &LeaderboardSettings,
    ) -> Result<EksAccess, FnError> {
        let eks = aws_sdk_eks::Client::new(sdk);
        let access = lb_aws::eks::describe_cluster(&eks, &deployment.cluster).await?;
        let region = sdk.region().map(|r| r.to_string()).unwrap_or_default();
        let credentials = sdk.credentials_provider().ok_or_else(|| {
            FnError::Config("no AWS credentials provider for the EKS token".into())
        })?;
        let tokens = TokenSource::new(&deployment.cluster, region, credentials);
        Ok(EksAccess {
            access,
            tokens: Arc::new(tokens),
            client: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_kubeconfig_s_client_is_built_once_and_kept() {
        let settings =
            lb_domain::settings::Settings::from_json(local_stack::stack::LOCAL_SETTINGS).unwrap();
        let deployment = settings.leaderboards.values().next().unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("kubeconfig");
        let yaml = "apiVersion: v1\nkind: Config\nclusters:\n- name: c\n  cluster:\n    server: \
                    http://127.0.0.1:1\nusers:\n- name: u\n  user: {}\ncontexts:\n- name: x\n  \
                    context: {cluster: c, user: u}\ncurrent-context: x\n";
        std::fs::write(&path, yaml).unwrap();
        let clusters = Clusters::kubeconfig(path.clone());
        clusters.connect(deployment).await.unwrap();
        // Gone from disk: a client rebuilt per invocation would fail to read it now.
        std::fs::remove_file(&path).unwrap();
        clusters.connect(deployment).await.unwrap();
        assert!(Clusters::kubeconfig(path)
            .connect(deployment)
            .await
            .is_err());
    }
}
