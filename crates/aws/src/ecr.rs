//! The participant's image in Amazon ECR: the digest its tag names now, read with
//! `DescribeImages` (the only call, and so the only permission, it needs).

use aws_config::SdkConfig;
use aws_sdk_ecr::error::ProvideErrorMetadata as _;
use aws_sdk_ecr::types::ImageIdentifier;
use aws_sdk_ecr::Client;

use crate::{AwsError, Result};

/// What the registry says of a tag.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Lookup {
    /// The digest (`sha256:...`) it names.
    Digest(String),
    /// No such image or repository: never pushed, or deleted.
    NotFound,
    /// The registry would not say (no permission on it): the tag stays as given.
    Refused(String),
}

/// ECR's client in `region` (an image's registry may be in any), with `sdk`'s credentials
/// and endpoint.
pub fn client(sdk: &SdkConfig, region: &str) -> Client {
    let config = aws_sdk_ecr::config::Builder::from(sdk)
        .region(aws_config::Region::new(region.to_owned()))
        .build();
    Client::from_conf(config)
}

/// ECR, in whichever region an image names.
#[derive(Debug, Clone)]
pub struct Registry {
    sdk: SdkConfig,
}

impl Registry {
    /// Registries reached with `sdk`'s credentials (and endpoint, in local mode).
    pub fn new(sdk: &SdkConfig) -> Registry {
        Registry { sdk: sdk.clone() }
    }

    /// The digest `tag` names now in `repository` of `registry` (an account id) in `region`
    /// (`lb_jobs::EcrTagged` has them).
    pub async fn digest_of(
        &self,
        (registry, region): (&str, &str),
        repository: &str,
        tag: &str,
    ) -> Result<Lookup> {
        let out = client(&self.sdk, region)
            .describe_images()
            .registry_id(registry)
            .repository_name(repository)
            .image_ids(ImageIdentifier::builder().image_tag(tag).build())
            .send()
            .await;
        let out = match out {
            Ok(out) => out,
            Err(e) => {
                let code = e
                    .as_service_error()
                    .and_then(|s| s.code().map(str::to_owned));
                return match code.as_deref() {
                    Some("ImageNotFoundException" | "RepositoryNotFoundException") => {
                        Ok(Lookup::NotFound)
                    }
                    Some("AccessDeniedException") => Ok(Lookup::Refused(
                        "no permission to read the repository's images".into(),
                    )),
                    _ => Err(AwsError::sdk("ecr", "DescribeImages", e)),
                };
            }
        };
        let digest = out
            .image_details()
            .iter()
            .find_map(|d| d.image_digest().map(str::to_owned));
        Ok(digest.map_or(Lookup::NotFound, Lookup::Digest))
    }
}
