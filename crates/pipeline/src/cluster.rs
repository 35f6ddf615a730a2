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
        /// Endpoint, CA and token source per cluster name.
        cache: Mutex<HashMap<String, (ClusterAccess, Arc<TokenSource>)>>,
    },
    /// One kubeconfig for every leaderboard (`LB_KUBECONFIG`).
    Kubeconfig(PathBuf),
}

impl Clusters {
    /// `LB_KUBECONFIG` when set (local mode), else EKS.
    pub fn from_env(sdk: &SdkConfig) -> Clusters {
        match std::env::var_os("LB_KUBECONFIG") {
            Some(path) if !path.is_empty() => Clusters::Kubeconfig(PathBuf::from(path)),
            _ => Clusters::eks(sdk),
        }
    }

    /// EKS access through `sdk`.
    pub fn eks(sdk: &SdkConfig) -> Clusters {
        Clusters::Eks {
            sdk: Box::new(sdk.clone()),
            cache: Mutex::new(HashMap::new()),
        }
    }

    /// A client for `deployment`'s cluster, in its namespace.
    pub async fn connect(&self, deployment: &LeaderboardSettings) -> Result<Cluster, FnError> {
        let cluster = match self {
            Clusters::Kubeconfig(path) => Cluster::from_kubeconfig(path, None).await?,
            Clusters::Eks { sdk, cache } => {
                let mut cache = cache.lock().await;
                if !cache.contains_key(&deployment.cluster) {
                    let eks = aws_sdk_eks::Client::new(sdk.as_ref());
                    let access = lb_aws::eks::describe_cluster(&eks, &deployment.cluster).await?;
                    let region = sdk.region().map(|r| r.to_string()).unwrap_or_default();
                    let credentials = sdk.credentials_provider().ok_or_else(|| {
                        FnError::Config("no AWS credentials provider for the EKS token".into())
                    })?;
                    let tokens = TokenSource::new(&deployment.cluster, region, credentials);
                    cache.insert(deployment.cluster.clone(), (access, Arc::new(tokens)));
                }
                let (access, tokens) = &cache[&deployment.cluster];
                let token = tokens.token().await?;
                Cluster::for_eks(&access.endpoint, &access.ca_pem, &token)?
            }
        };
        Ok(cluster.with_namespace(&deployment.namespace))
    }
}
