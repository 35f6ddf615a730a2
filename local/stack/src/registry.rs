//! The participants' registry on moto's ECR: an image pushed under its tag as `evalai push`
//! leaves it, so that Intake resolves the tag to a digest as it does in the deployment.

use aws_config::SdkConfig;
use aws_sdk_ecr::error::ProvideErrorMetadata as _;
use serde_json::json;
use sha2::{Digest as _, Sha256};

use crate::StackError;

fn failed(what: String) -> impl FnOnce(Box<dyn std::error::Error + Send + Sync>) -> StackError {
    move |source| StackError::Provision { what, source }
}

/// Pushes `image` (an ECR reference by tag) as an image of no layers: its repository is
/// created when missing. The digest ECR gives it; `None` for a reference that is not an ECR
/// tag (nothing to push).
pub async fn push(sdk: &SdkConfig, image: &str) -> Result<Option<String>, StackError> {
    let reference = lb_jobs::parse_image(image).map_err(|e| failed(image.to_owned())(e.into()))?;
    let Some(ecr) = reference.ecr_tagged() else {
        return Ok(None);
    };
    let client = lb_aws::ecr::client(sdk, ecr.region);
    let created = client
        .create_repository()
        .registry_id(ecr.registry)
        .repository_name(ecr.repository)
        .send()
        .await;
    if let Err(e) = created {
        if e.as_service_error().and_then(|s| s.code()) != Some("RepositoryAlreadyExistsException") {
            return Err(failed(format!("ECR repository `{}`", ecr.repository))(
                e.into(),
            ));
        }
    }
    // A manifest of its own per reference: another tag is another image.
    let config_digest: String = Sha256::digest(image.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    let manifest = json!({
        "schemaVersion": 2,
        "mediaType": "application/vnd.docker.distribution.manifest.v2+json",
        "config": {
            "mediaType": "application/vnd.docker.container.image.v1+json",
            "size": 0,
            "digest": format!("sha256:{config_digest}"),
        },
        "layers": [],
    });
    let out = client
        .put_image()
        .registry_id(ecr.registry)
        .repository_name(ecr.repository)
        .image_tag(ecr.tag)
        .image_manifest(manifest.to_string())
        .send()
        .await
        .map_err(|e| failed(format!("ECR image `{image}`"))(e.into()))?;
    Ok(out
        .image()
        .and_then(|i| i.image_id())
        .and_then(|id| id.image_digest())
        .map(str::to_owned))
}
