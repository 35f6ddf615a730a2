//! Shared helpers for the fake EvalAI integration tests.
#![allow(dead_code)]

use std::time::Duration;

use reqwest::header::HeaderMap;
use reqwest::{Method, StatusCode};
use serde_json::Value;

/// Results of `a_4workers_20routes_finished` (Leaderboard 2.0, the 15 labels in order).
pub const LB2_RESULTS: &str = r#"[{"split": "leaderboard", "show_to_participant": true, "accuracies": {"Driving score": 23.699655, "Route completion": 62.1875, "Infraction penalty": 0.390282, "Collisions pedestrians": 0.0, "Collisions vehicles": 0.134, "Collisions layout": 0.089, "Red light infractions": 0.328, "Stop sign infractions": 0.06, "Off-road infractions": 2.273, "Route deviations": 0.03, "Route timeouts": 0.03, "Agent blocked": 0.104, "Yield emergency vehicle infractions": 0.045, "Scenario timeouts": 0.074, "Min speed infractions": 0.328}}]"#;

/// A request body.
pub enum Body {
    None,
    Json(Value),
    Form(&'static str),
    Raw(&'static str, Vec<u8>),
}

/// A response, read fully.
#[derive(Debug)]
pub struct Resp {
    pub status: StatusCode,
    pub headers: HeaderMap,
    pub text: String,
}

impl Resp {
    pub fn json(&self) -> Value {
        serde_json::from_str(&self.text).unwrap_or_else(|e| panic!("not JSON ({e}): {}", self.text))
    }

    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.get(name).and_then(|v| v.to_str().ok())
    }

    pub fn content_type(&self) -> &str {
        self.header("content-type").unwrap_or("")
    }

    pub fn is_html(&self) -> bool {
        self.content_type().starts_with("text/html")
    }
}

/// A reqwest client that never follows redirects and never waits long.
pub struct Api {
    http: reqwest::Client,
    pub base: String,
}

impl Api {
    pub fn new(base: String) -> Api {
        let http = reqwest::Client::builder()
            .redirect(reqwest::redirect::Policy::none())
            .timeout(Duration::from_secs(10))
            .build()
            .expect("client");
        Api { http, base }
    }

    pub async fn send(&self, method: Method, path: &str, auth: Option<&str>, body: Body) -> Resp {
        let mut req = self.http.request(method, format!("{}{}", self.base, path));
        if let Some(a) = auth {
            req = req.header("Authorization", a);
        }
        req = match body {
            Body::None => req,
            Body::Json(v) => req
                .header("Content-Type", "application/json")
                .body(v.to_string()),
            Body::Form(f) => req
                .header("Content-Type", "application/x-www-form-urlencoded")
                .body(f),
            Body::Raw(ct, bytes) => {
                let req = if ct.is_empty() {
                    req
                } else {
                    req.header("Content-Type", ct)
                };
                req.body(bytes)
            }
        };
        let resp = req.send().await.expect("request sent");
        let status = resp.status();
        let headers = resp.headers().clone();
        let text = resp.text().await.expect("body read");
        Resp {
            status,
            headers,
            text,
        }
    }

    pub async fn get(&self, path: &str, auth: Option<&str>) -> Resp {
        self.send(Method::GET, path, auth, Body::None).await
    }

    pub async fn put_json(&self, path: &str, auth: &str, v: Value) -> Resp {
        self.send(Method::PUT, path, Some(auth), Body::Json(v))
            .await
    }

    pub async fn patch_json(&self, path: &str, auth: &str, v: Value) -> Resp {
        self.send(Method::PATCH, path, Some(auth), Body::Json(v))
            .await
    }
}

pub const HOST: &str = "Bearer host-token";
pub const PARTICIPANT: &str = "Bearer participant-token";
pub const OTHER: &str = "Bearer other-participant-token";
pub const UPDATE: &str = "/api/jobs/challenge/1/update_submission/";
pub const PARTIAL: &str = "/api/jobs/challenges/1/update_partially_evaluated_submission/";
