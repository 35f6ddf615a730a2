//! The participant's image in Amazon ECR: the digest its tag names now, read with
//! `DescribeImages` (the only call, and so the only permission, it needs).

use aws_config::SdkConfig;
use aws_sdk_ecr::error::ProvideErrorMetadata as _;
use aws_sdk_ecr::types::ImageIdentifier;
use aws_sdk_ecr::Client;

use crate::{AwsError, Result};

/// A repository of ECR, as an image reference names it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Repository<'a> {
    /// The registry (its AWS account id).
    pub registry: &'a str,
    /// Its region.
    pub region: &'a str,
    /// The repository's name.
    pub name: &'a str,
}

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

    /// The digest `tag` names in `repository` now.
    pub async fn digest_of(&self, repository: &Repository<'_>, tag: &str) -> Result<Lookup> {
        let config = aws_sdk_ecr::config::Builder::from(&self.sdk)
            .region(aws_config::Region::new(repository.region.to_owned()))
            .build();
        let out = Client::from_conf(config)
            .describe_images()
            .registry_id(repository.registry)
            .repository_name(repository.name)
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
