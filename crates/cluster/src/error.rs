//! One error type for the Kubernetes adapter; kube's error stays the source.

use std::time::Duration;

/// Result alias of this crate.
pub type Result<T, E = ClusterError> = std::result::Result<T, E>;

/// What went wrong talking to Kubernetes; `name()` is what the state machine matches.
#[derive(Debug, thiserror::Error)]
pub enum ClusterError {
    /// The kubeconfig, endpoint, CA or token cannot make a client.
    #[error("cannot configure the Kubernetes client: {problem}")]
    Config {
        /// What is wrong (never the token).
        problem: String,
        /// The underlying error, when there is one.
        #[source]
        source: Option<Box<dyn std::error::Error + Send + Sync>>,
    },
    /// The submission id cannot be a label value (it would change the selector).
    #[error("submission id `{id}` is not a valid Kubernetes label value")]
    InvalidSubmissionId {
        /// The refused id (cut to 80 characters).
        id: String,
    },
    /// The Job we were asked to create is not one this adapter can track.
    #[error("Job `{job}` cannot be launched: {problem}")]
    InvalidJobSpec {
        /// Its name (or `<unnamed>`).
        job: String,
        /// What is missing or inconsistent.
        problem: String,
    },
    /// A Job of that name exists and belongs to another submission (or to no submission).
    #[error(
        "Job `{job}` already exists and belongs to submission `{owner}`, not `{submission_id}`"
    )]
    JobNameTaken {
        /// The Job name.
        job: String,
        /// The submission we launch.
        submission_id: String,
        /// The submission label of the existing Job (`<none>` when unlabelled).
        owner: String,
    },
    /// A Job of that name of this submission is being deleted; a new one can be created once
    /// it is gone.
    #[error("Job `{job}` of submission `{submission_id}` is still being deleted; retry later")]
    JobTerminating {
        /// The Job name.
        job: String,
        /// The submission.
        submission_id: String,
    },
    /// The API server refused the object as invalid (422); retrying cannot help.
    #[error("Kubernetes refused {what} as invalid: {cause}")]
    Invalid {
        /// What was sent (e.g. "Job `lb-1-x-0`").
        what: String,
        /// The causes from the Status details (`field: message; ...`), or its message.
        cause: String,
        /// kube's error.
        #[source]
        source: Box<kube::Error>,
    },
    /// 403: the identity may not do this (RBAC, EKS access entries, a forbidden namespace).
    #[error("Kubernetes forbids `{operation}`: {message}")]
    Forbidden {
        /// e.g. `create job`.
        operation: &'static str,
        /// The server's message.
        message: String,
        /// kube's error.
        #[source]
        source: Box<kube::Error>,
    },
    /// 401: the token is missing, wrong or expired.
    #[error("Kubernetes did not accept the credentials for `{operation}`")]
    Unauthorized {
        /// e.g. `list pods`.
        operation: &'static str,
        /// kube's error.
        #[source]
        source: Box<kube::Error>,
    },
    /// The server answered 429, 5xx or a server-side timeout: retry later.
    #[error("Kubernetes `{operation}` failed transiently (HTTP {code}: {message})")]
    Transient {
        /// e.g. `create job`.
        operation: &'static str,
        /// HTTP status code.
        code: u16,
        /// The server's message.
        message: String,
        /// kube's error.
        #[source]
        source: Box<kube::Error>,
    },
    /// The server could not be reached or did not answer in time: retry later.
    #[error("Kubernetes API unreachable during `{operation}`")]
    Unavailable {
        /// e.g. `delete job`.
        operation: &'static str,
        /// kube's error (connection, TLS, hyper timeout).
        #[source]
        source: Box<kube::Error>,
    },
    /// Our own bound on one API call elapsed.
    #[error("Kubernetes `{operation}` did not finish within {limit:?}")]
    Timeout {
        /// e.g. `get job`.
        operation: &'static str,
        /// The bound.
        limit: Duration,
    },
    /// Any other answer (400, 404 on create, an unexpected 409, ...).
    #[error("Kubernetes `{operation}` failed (HTTP {code} {reason}: {message})")]
    Request {
        /// e.g. `create job`.
        operation: &'static str,
        /// HTTP status code (0 when the server sent none).
        code: u16,
        /// The Status reason, e.g. `BadRequest`.
        reason: String,
        /// The server's message.
        message: String,
        /// kube's error.
        #[source]
        source: Box<kube::Error>,
    },
    /// The answer could not be decoded, or kube failed locally.
    #[error("Kubernetes `{operation}` gave an unusable answer")]
    Malformed {
        /// e.g. `list jobs`.
        operation: &'static str,
        /// kube's error.
        #[source]
        source: Box<kube::Error>,
    },
}

lb_domain::error_names!(ClusterError {
    Config => "KubeConfigInvalid";
    InvalidSubmissionId => "InvalidSubmissionId";
    InvalidJobSpec => "InvalidJobSpec";
    JobNameTaken => "JobNameTaken";
    JobTerminating => "JobTerminating" [transient];
    Invalid => "KubeInvalid";
    Forbidden => "KubeForbidden";
    Unauthorized => "KubeUnauthorized";
    Transient => "KubeTransient" [transient];
    Unavailable => "KubeUnavailable" [transient];
    Timeout => "KubeTimeout" [transient];
    Request => "KubeRequestFailed";
    Malformed => "KubeResponseMalformed";
});

impl ClusterError {
    /// Classifies a kube error of `operation`. 404 and 409 are handled by the callers that
    /// expect them; here they are plain request failures.
    pub(crate) fn from_kube(operation: &'static str, what: &str, err: kube::Error) -> Self {
        match &err {
            kube::Error::Api(status) => {
                let code = status.code;
                let reason = status.reason.as_str();
                if code == 401 || reason == "Unauthorized" {
                    ClusterError::Unauthorized {
                        operation,
                        source: Box::new(err),
                    }
                } else if code == 403 || reason == "Forbidden" {
                    let message = status.message.clone();
                    ClusterError::Forbidden {
                        operation,
                        message,
                        source: Box::new(err),
                    }
                } else if code == 422 || reason == "Invalid" {
                    let cause = invalid_cause(status);
                    ClusterError::Invalid {
                        what: what.to_string(),
                        cause,
                        source: Box::new(err),
                    }
                } else if code == 429
                    || (500..600).contains(&code)
                    || matches!(
                        reason,
                        "TooManyRequests"
                            | "ServerTimeout"
                            | "Timeout"
                            | "InternalError"
                            | "ServiceUnavailable"
                    )
                {
                    let message = status.message.clone();
                    ClusterError::Transient {
                        operation,
                        code,
                        message,
                        source: Box::new(err),
                    }
                } else {
                    let (reason, message) = (status.reason.clone(), status.message.clone());
                    ClusterError::Request {
                        operation,
                        code,
                        reason,
                        message,
                        source: Box::new(err),
                    }
                }
            }
            kube::Error::HyperError(_) | kube::Error::Service(_) => ClusterError::Unavailable {
                operation,
                source: Box::new(err),
            },
            _ => ClusterError::Malformed {
                operation,
                source: Box::new(err),
            },
        }
    }
}

/// `field: message; ...` from a 422 Status, or its message when it lists no causes.
fn invalid_cause(status: &kube::core::Status) -> String {
    let causes: Vec<String> = status
        .details
        .iter()
        .flat_map(|d| d.causes.iter())
        .map(|c| match (c.field.is_empty(), c.message.is_empty()) {
            (false, false) => format!("{}: {}", c.field, c.message),
            (true, false) => c.message.clone(),
            (false, true) => format!("{}: {}", c.field, c.reason),
            (true, true) => c.reason.clone(),
        })
        .filter(|s| !s.is_empty())
        .collect();
    if causes.is_empty() {
        status.message.clone()
    } else {
        causes.join("; ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use kube::core::response::{StatusCause, StatusDetails};
    use kube::core::Status;

    fn api(status: Status) -> kube::Error {
        kube::Error::Api(status.boxed())
    }

    #[test]
    fn status_codes_map_to_stable_names_and_transience() {
        let cases = [
            (401, "Unauthorized", "KubeUnauthorized", false),
            (403, "Forbidden", "KubeForbidden", false),
            (422, "Invalid", "KubeInvalid", false),
            (429, "TooManyRequests", "KubeTransient", true),
            (500, "InternalError", "KubeTransient", true),
            (503, "ServiceUnavailable", "KubeTransient", true),
            (504, "Timeout", "KubeTransient", true),
            (400, "BadRequest", "KubeRequestFailed", false),
            (404, "NotFound", "KubeRequestFailed", false),
        ];
        for (code, reason, name, transient) in cases {
            let e = ClusterError::from_kube(
                "create job",
                "Job `j`",
                api(Status::failure("m", reason).with_code(code)),
            );
            assert_eq!(e.name(), name, "{code}");
            assert_eq!(e.is_transient(), transient, "{code}");
        }
    }

    #[test]
    fn a_server_timeout_reason_without_a_code_is_transient() {
        let e = ClusterError::from_kube(
            "list pods",
            "",
            api(Status::failure("slow", "ServerTimeout")),
        );
        assert_eq!(e.name(), "KubeTransient");
    }

    #[test]
    fn an_invalid_status_names_every_cause() {
        let status = Status::failure("Job.batch \"x\" is invalid", "Invalid")
            .with_code(422)
            .with_details(StatusDetails {
                name: "x".into(),
                group: "batch".into(),
                kind: "Job".into(),
                uid: String::new(),
                causes: vec![
                    StatusCause {
                        reason: "FieldValueRequired".into(),
                        message: "Required value".into(),
                        field: "spec.template.spec.containers[0].image".into(),
                    },
                    StatusCause {
                        reason: "FieldValueInvalid".into(),
                        message: String::new(),
                        field: "metadata.name".into(),
                    },
                ],
                retry_after_seconds: 0,
            });
        let e = ClusterError::from_kube("create job", "Job `x`", api(status));
        let text = e.to_string();
        assert!(
            text.contains("spec.template.spec.containers[0].image: Required value; metadata.name: FieldValueInvalid"),
            "{text}"
        );
        assert!(std::error::Error::source(&e).is_some());
    }

    #[test]
    fn an_invalid_status_without_causes_keeps_its_message() {
        let status = Status::failure("Job.batch \"x\" is invalid: oops", "Invalid").with_code(422);
        let e = ClusterError::from_kube("create job", "Job `x`", api(status));
        assert!(
            e.to_string().ends_with("Job.batch \"x\" is invalid: oops"),
            "{e}"
        );
    }

    #[test]
    fn decoding_failures_are_malformed_not_transient() {
        let serde = serde_json::from_str::<u8>("x").unwrap_err();
        let e = ClusterError::from_kube("list jobs", "", kube::Error::SerdeError(serde));
        assert_eq!(e.name(), "KubeResponseMalformed");
        assert!(!e.is_transient());
    }
}
