//! The two secrets: the operator's settings and the EvalAI host token, read once per cold start.
//!
//! They are separate so that only the functions that talk to EvalAI may read the token
//! (IAM per secret), and so rotating the token does not touch the settings.

use aws_sdk_secretsmanager::Client;
use lb_domain::settings::Settings;
use lb_evalai::HostToken;
use serde_json::Value;

use crate::{AwsError, Result};

/// Reads a secret's string value.
async fn secret_string(client: &Client, id: &str) -> Result<String> {
    let out = client
        .get_secret_value()
        .secret_id(id)
        .send()
        .await
        .map_err(|e| AwsError::sdk("secretsmanager", "GetSecretValue", e))?;
    out.secret_string.ok_or_else(|| AwsError::InvalidSecret {
        id: id.to_string(),
        problem: "it has no string value (binary secrets are not supported)".into(),
    })
}

/// Loads and checks the settings secret (layout in the README, "Configuration").
pub async fn load_settings(client: &Client, id: &str) -> Result<Settings> {
    let text = secret_string(client, id).await?;
    Settings::from_json(&text).map_err(|e| AwsError::InvalidSecret {
        id: id.to_string(),
        problem: e.to_string(),
    })
}

/// Loads the EvalAI host token: `{"token": "..."}` or the bare token string.
pub async fn load_token(client: &Client, id: &str) -> Result<HostToken> {
    let text = secret_string(client, id).await?;
    parse_token(id, &text)
}

/// The token out of the secret's text; errors never include the value.
pub fn parse_token(id: &str, text: &str) -> Result<HostToken> {
    let invalid = |problem: &str| AwsError::InvalidSecret {
        id: id.to_string(),
        problem: problem.to_string(),
    };
    let token = match serde_json::from_str::<Value>(text) {
        Ok(Value::Object(map)) => match map.get("token") {
            Some(Value::String(s)) => s.clone(),
            _ => return Err(invalid("the JSON has no string `token` key")),
        },
        Ok(Value::String(s)) => s,
        Ok(_) => return Err(invalid("expected `{\"token\": \"...\"}` or a bare token")),
        Err(_) => text.trim().to_string(),
    };
    if token.is_empty() || token.chars().any(|c| c.is_whitespace() || c.is_control()) {
        return Err(invalid("the token is empty or holds whitespace"));
    }
    Ok(HostToken::new(token))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_token_is_read_from_json_or_bare_text_and_never_shown() {
        assert_eq!(
            parse_token("t", r#"{"token": "abc.def"}"#)
                .unwrap()
                .expose(),
            "abc.def"
        );
        assert_eq!(parse_token("t", "abc.def\n").unwrap().expose(), "abc.def");
        assert_eq!(
            format!("{:?}", parse_token("t", "abc").unwrap()),
            "HostToken(***)"
        );
        let err = parse_token("t", r#"{"tok": "abc"}"#).unwrap_err();
        assert_eq!(err.name(), "InvalidSecret");
        let err = parse_token("t", r#"{"token": "a b"}"#).unwrap_err();
        assert!(!err.to_string().contains("a b"));
    }
}
