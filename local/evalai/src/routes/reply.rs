//! What a view answers, before it becomes an HTTP response.

use axum::body::Body;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::Response;

use crate::html;
use crate::pyjson::PyValue;

/// Body kinds EvalAI produces.
#[derive(Debug, Clone)]
pub(crate) enum ReplyBody {
    /// DRF's compact JSON.
    Json(PyValue),
    /// A Django HTML page.
    Html(&'static str),
    /// No body (204, 301).
    Empty,
    /// A stored file, verbatim (its content type is in `headers`).
    Raw(String),
}

/// A view's answer plus what the request log should know about it.
#[derive(Debug, Clone)]
pub(crate) struct Reply {
    pub status: StatusCode,
    pub body: ReplyBody,
    pub headers: Vec<(header::HeaderName, String)>,
    /// The Python exception behind an HTML 500.
    pub error: Option<String>,
}

impl Reply {
    pub fn json(status: StatusCode, value: PyValue) -> Reply {
        Reply {
            status,
            body: ReplyBody::Json(value),
            headers: Vec::new(),
            error: None,
        }
    }

    /// `{"error": text}`, the shape EvalAI's views use.
    pub fn error(status: StatusCode, text: impl Into<String>) -> Reply {
        Reply::json(
            status,
            PyValue::dict(vec![("error", PyValue::Str(text.into()))]),
        )
    }

    /// `{"detail": text}`, the shape of DRF framework errors.
    pub fn detail(status: StatusCode, text: impl Into<String>) -> Reply {
        Reply::json(
            status,
            PyValue::dict(vec![("detail", PyValue::Str(text.into()))]),
        )
    }

    /// `{"success": "Submission result has been successfully updated"}`.
    pub fn success_updated() -> Reply {
        Reply::json(
            StatusCode::OK,
            PyValue::dict(vec![(
                "success",
                PyValue::str("Submission result has been successfully updated"),
            )]),
        )
    }

    /// An unhandled exception: Django's HTML 500 page.
    pub fn server_error(exception: impl Into<String>) -> Reply {
        Reply {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            body: ReplyBody::Html(html::SERVER_ERROR),
            headers: Vec::new(),
            error: Some(exception.into()),
        }
    }

    /// An unresolved URL: Django's HTML 404 page.
    pub fn not_found_page() -> Reply {
        Reply {
            status: StatusCode::NOT_FOUND,
            body: ReplyBody::Html(html::NOT_FOUND),
            headers: Vec::new(),
            error: None,
        }
    }

    /// APPEND_SLASH's permanent redirect.
    pub fn redirect(location: String) -> Reply {
        Reply {
            status: StatusCode::MOVED_PERMANENTLY,
            body: ReplyBody::Empty,
            headers: vec![(header::LOCATION, location)],
            error: None,
        }
    }

    /// The DRF 429 with `Retry-After`.
    pub fn throttled(wait: u64) -> Reply {
        let unit = if wait == 1 { "second" } else { "seconds" };
        let mut r = Reply::detail(
            StatusCode::TOO_MANY_REQUESTS,
            format!("Request was throttled. Expected available in {wait} {unit}."),
        );
        r.headers.push((header::RETRY_AFTER, wait.to_string()));
        r
    }

    pub fn with_header(mut self, name: header::HeaderName, value: impl Into<String>) -> Reply {
        self.headers.push((name, value.into()));
        self
    }

    /// Renders the HTTP response (`head` drops the body, as Django does for HEAD).
    pub fn into_response(self, head: bool) -> Response {
        let (content_type, bytes): (Option<&str>, Vec<u8>) = match &self.body {
            ReplyBody::Json(v) => (Some("application/json"), v.dumps().into_bytes()),
            ReplyBody::Html(page) => (Some(html::CONTENT_TYPE), page.as_bytes().to_vec()),
            ReplyBody::Empty if self.status == StatusCode::MOVED_PERMANENTLY => {
                (Some(html::CONTENT_TYPE), Vec::new())
            }
            ReplyBody::Empty => (None, Vec::new()),
            ReplyBody::Raw(text) => (None, text.as_bytes().to_vec()),
        };
        let len = bytes.len();
        let mut response = Response::new(if head {
            Body::empty()
        } else {
            Body::from(bytes)
        });
        *response.status_mut() = self.status;
        let headers = response.headers_mut();
        if let Some(ct) = content_type {
            headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(ct));
        }
        if head {
            headers.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
        }
        for (name, value) in self.headers {
            if let Ok(v) = HeaderValue::from_str(&value) {
                headers.append(name, v);
            }
        }
        response
    }
}

/// `Result` whose error short-circuits a view with a finished reply.
pub(crate) type ViewResult<T = Reply> = Result<T, Reply>;
