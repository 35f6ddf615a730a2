//! EKS access: the cluster endpoint and CA from `DescribeCluster`, and the standard EKS IAM
//! bearer token, refreshed before it expires; a GPU node group's maximum.
//!
//! The token is `k8s-aws-v1.` + base64url (no padding) of a presigned STS
//! `GetCallerIdentity` URL whose signature covers the `x-k8s-aws-id: <cluster>` header, as
//! `aws eks get-token` and aws-iam-authenticator make it. EKS accepts it for 15 minutes.

use std::time::{Duration, Instant, SystemTime};

use aws_credential_types::provider::{ProvideCredentials, SharedCredentialsProvider};
use aws_credential_types::Credentials;
use aws_sigv4::http_request::{
    sign, SignableBody, SignableRequest, SignatureLocation, SigningSettings,
};
use aws_sigv4::sign::v4;
use base64::Engine;
use tokio::sync::Mutex;

use crate::{AwsError, Result};

/// Where the cluster's API server is and how to trust it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ClusterAccess {
    /// `https://<id>.<region>.eks.amazonaws.com`.
    pub endpoint: String,
    /// The cluster CA, PEM.
    pub ca_pem: Vec<u8>,
}

/// Reads the endpoint and CA of cluster `name`.
pub async fn describe_cluster(client: &aws_sdk_eks::Client, name: &str) -> Result<ClusterAccess> {
    let out = client
        .describe_cluster()
        .name(name)
        .send()
        .await
        .map_err(|e| AwsError::sdk("eks", "DescribeCluster", e))?;
    let malformed = |problem: &str| AwsError::Malformed {
        what: format!("EKS cluster `{name}`"),
        problem: problem.to_string(),
    };
    let cluster = out
        .cluster
        .ok_or_else(|| malformed("no cluster in the answer"))?;
    let endpoint = cluster
        .endpoint
        .ok_or_else(|| malformed("no endpoint (is the cluster still being created?)"))?;
    let ca = cluster
        .certificate_authority
        .and_then(|ca| ca.data)
        .ok_or_else(|| malformed("no certificate authority data"))?;
    let ca_pem = base64::engine::general_purpose::STANDARD
        .decode(ca.trim())
        .map_err(|e| malformed(&format!("certificate authority data is not base64: {e}")))?;
    Ok(ClusterAccess { endpoint, ca_pem })
}

/// The most nodes managed node group `nodegroup` of cluster `cluster` may grow to (its
/// scaling configuration's `maxSize`); none when the group does not exist.
pub async fn nodegroup_max(
    client: &aws_sdk_eks::Client,
    cluster: &str,
    nodegroup: &str,
) -> Result<Option<u32>> {
    let out = client
        .describe_nodegroup()
        .cluster_name(cluster)
        .nodegroup_name(nodegroup)
        .send()
        .await;
    match out {
        Ok(out) => Ok(out
            .nodegroup
            .and_then(|g| g.scaling_config?.max_size)
            .and_then(|max| u32::try_from(max).ok())),
        Err(e)
            if e.as_service_error()
                .is_some_and(|s| s.is_resource_not_found_exception()) =>
        {
            Ok(None)
        }
        Err(e) => Err(AwsError::sdk("eks", "DescribeNodegroup", e)),
    }
}

/// How long EKS accepts a token.
pub const TOKEN_LIFETIME: Duration = Duration::from_secs(15 * 60);
/// We make a new one when the cached one is this old, well before EKS refuses it.
pub const TOKEN_REFRESH_AFTER: Duration = Duration::from_secs(10 * 60);

/// Makes EKS bearer tokens from the function's credentials and caches them.
#[derive(Debug)]
pub struct TokenSource {
    cluster: String,
    region: String,
    credentials: SharedCredentialsProvider,
    cached: Mutex<Option<(String, Instant)>>,
}

impl TokenSource {
    /// A token source for `cluster` in `region`.
    pub fn new(
        cluster: impl Into<String>,
        region: impl Into<String>,
        credentials: SharedCredentialsProvider,
    ) -> Self {
        TokenSource {
            cluster: cluster.into(),
            region: region.into(),
            credentials,
            cached: Mutex::new(None),
        }
    }

    /// A valid token: the cached one while young enough, else a fresh one.
    pub async fn token(&self) -> Result<String> {
        let mut cached = self.cached.lock().await;
        if let Some((token, made)) = cached.as_ref() {
            if made.elapsed() < TOKEN_REFRESH_AFTER {
                return Ok(token.clone());
            }
        }
        let credentials =
            self.credentials
                .provide_credentials()
                .await
                .map_err(|e| AwsError::Transient {
                    service: "sts",
                    operation: "credentials",
                    source: Box::new(e),
                })?;
        let token = presign_token(&self.cluster, &self.region, &credentials, SystemTime::now())?;
        *cached = Some((token.clone(), Instant::now()));
        Ok(token)
    }
}

/// The EKS token for `cluster`, signed at `time`.
pub fn presign_token(
    cluster: &str,
    region: &str,
    credentials: &Credentials,
    time: SystemTime,
) -> Result<String> {
    let host = format!("sts.{region}.amazonaws.com");
    let url = format!("https://{host}/?Action=GetCallerIdentity&Version=2011-06-15");
    let signing_error = |e: &dyn std::fmt::Display| AwsError::Malformed {
        what: "EKS token".into(),
        problem: e.to_string(),
    };
    let mut settings = SigningSettings::default();
    settings.signature_location = SignatureLocation::QueryParams;
    settings.expires_in = Some(Duration::from_secs(60));
    let identity = credentials.clone().into();
    let params = v4::SigningParams::builder()
        .identity(&identity)
        .region(region)
        .name("sts")
        .time(time)
        .settings(settings)
        .build()
        .map_err(|e| signing_error(&e))?
        .into();
    let headers = [("host", host.as_str()), ("x-k8s-aws-id", cluster)];
    let signable = SignableRequest::new(
        "GET",
        url.as_str(),
        headers.into_iter(),
        SignableBody::Bytes(&[]),
    )
    .map_err(|e| signing_error(&e))?;
    let (instructions, _signature) = sign(signable, &params)
        .map_err(|e| signing_error(&e))?
        .into_parts();
    let mut request = http::Request::get(&url)
        .body(())
        .map_err(|e| signing_error(&e))?;
    instructions.apply_to_request_http1x(&mut request);
    let presigned = request.uri().to_string();
    Ok(format!(
        "k8s-aws-v1.{}",
        base64::engine::general_purpose::URL_SAFE_NO_PAD.encode(presigned)
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(token: &str) -> String {
        let body = token.strip_prefix("k8s-aws-v1.").expect("prefix");
        String::from_utf8(
            base64::engine::general_purpose::URL_SAFE_NO_PAD
                .decode(body)
                .unwrap(),
        )
        .unwrap()
    }

    #[test]
    fn the_token_is_a_presigned_sts_url_covering_the_cluster_header() {
        let credentials = Credentials::new("AKIDEXAMPLE", "secret", None, None, "test");
        let time = SystemTime::UNIX_EPOCH + Duration::from_secs(1_700_000_000);
        let token = presign_token("leaderboard-20", "us-west-2", &credentials, time).unwrap();
        assert!(!token.contains('='), "no padding: {token}");
        let url = decode(&token);
        assert!(
            url.starts_with(
                "https://sts.us-west-2.amazonaws.com/?Action=GetCallerIdentity&Version=2011-06-15&"
            ),
            "{url}"
        );
        for part in [
            "X-Amz-Algorithm=AWS4-HMAC-SHA256",
            "X-Amz-Credential=AKIDEXAMPLE%2F20231114%2Fus-west-2%2Fsts%2Faws4_request",
            "X-Amz-Date=20231114T221320Z",
            "X-Amz-Expires=60",
            "X-Amz-SignedHeaders=host%3Bx-k8s-aws-id",
            "X-Amz-Signature=",
        ] {
            assert!(url.contains(part), "{part} missing in {url}");
        }
        assert!(!url.contains("secret"));
        // Deterministic for a given time, different for another cluster.
        assert_eq!(
            token,
            presign_token("leaderboard-20", "us-west-2", &credentials, time).unwrap()
        );
        assert_ne!(
            token,
            presign_token("leaderboard-10", "us-west-2", &credentials, time).unwrap()
        );
    }

    #[test]
    fn a_session_token_is_carried_in_the_url() {
        let credentials =
            Credentials::new("AKID", "secret", Some("SESSION/TOKEN".into()), None, "test");
        let url =
            decode(&presign_token("c", "eu-west-1", &credentials, SystemTime::now()).unwrap());
        assert!(
            url.contains("X-Amz-Security-Token=SESSION%2FTOKEN"),
            "{url}"
        );
    }

    #[tokio::test]
    async fn the_cached_token_is_reused_until_it_is_old() {
        let provider =
            SharedCredentialsProvider::new(Credentials::new("AKID", "secret", None, None, "test"));
        let source = TokenSource::new("c", "us-east-1", provider);
        let first = source.token().await.unwrap();
        assert_eq!(first, source.token().await.unwrap());
        // Age the cache past the refresh point: the next call signs anew.
        source.cached.lock().await.as_mut().unwrap().1 =
            Instant::now() - TOKEN_REFRESH_AFTER - Duration::from_secs(1);
        tokio::time::sleep(Duration::from_millis(1100)).await;
        assert_ne!(first, source.token().await.unwrap());
    }
}
