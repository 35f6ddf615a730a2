//! Authentication as EvalAI configures it: simplejwt (`Bearer`), then the legacy `Token` scheme.

use crate::fixture::TokenKind;
use crate::pyjson::PyValue;
use crate::state::World;

/// Value of `WWW-Authenticate` on every 401 (simplejwt's `authenticate_header`).
pub const WWW_AUTHENTICATE: &str = "Bearer realm=\"api\"";

/// Why authentication failed; each renders to EvalAI's exact 401 body.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum AuthFailure {
    /// No header, or a scheme neither class knows.
    NotProvided,
    /// `Bearer` with zero or several values.
    BearerHeader,
    /// Bearer value that is not a valid refresh token; the message per token class.
    TokenNotValid(&'static str),
    /// simplejwt: the token's user is inactive.
    JwtUserInactive,
    /// `Token` with no value.
    LegacyNoCredentials,
    /// `Token` with several values.
    LegacySpaces,
    /// Unknown legacy key (or a JWT after `Token`).
    LegacyInvalid,
    /// Legacy key of an inactive user.
    LegacyUserInactive,
    /// Expired legacy key.
    LegacyExpired,
}

impl AuthFailure {
    /// The JSON body EvalAI answers with.
    pub fn body(&self) -> PyValue {
        let detail = |text: &str| PyValue::dict(vec![("detail", PyValue::str(text))]);
        match self {
            AuthFailure::NotProvided => detail("Authentication credentials were not provided."),
            AuthFailure::BearerHeader => {
                detail("Authorization header must contain two space-delimited values")
            }
            AuthFailure::TokenNotValid(message) => PyValue::dict(vec![
                (
                    "detail",
                    PyValue::str("Given token not valid for any token type"),
                ),
                ("code", PyValue::str("token_not_valid")),
                (
                    "messages",
                    PyValue::List(vec![PyValue::dict(vec![
                        ("token_class", PyValue::str("RefreshToken")),
                        ("token_type", PyValue::str("refresh")),
                        ("message", PyValue::str(*message)),
                    ])]),
                ),
            ]),
            AuthFailure::JwtUserInactive => detail("User is inactive"),
            AuthFailure::LegacyNoCredentials => {
                detail("Invalid token header. No credentials provided.")
            }
            AuthFailure::LegacySpaces => {
                detail("Invalid token header. Token string should not contain spaces.")
            }
            AuthFailure::LegacyInvalid => detail("Invalid token"),
            AuthFailure::LegacyUserInactive => detail("User inactive or deleted"),
            AuthFailure::LegacyExpired => detail("Token has expired"),
        }
    }
}

/// Python's `bytes.split()`: ASCII whitespace separated, empty parts dropped.
fn split_header(header: &[u8]) -> Vec<&[u8]> {
    header
        .split(|b| matches!(b, b' ' | b'\t' | b'\n' | b'\r' | 0x0b | 0x0c))
        .filter(|p| !p.is_empty())
        .collect()
}

/// Runs the two authentication classes in order; returns the user id.
pub(crate) fn authenticate(world: &World, header: Option<&[u8]>) -> Result<u64, AuthFailure> {
    let Some(header) = header else {
        return Err(AuthFailure::NotProvided);
    };
    let parts = split_header(header);
    let Some(scheme) = parts.first() else {
        return Err(AuthFailure::NotProvided);
    };
    // 1. simplejwt: the scheme must be exactly `Bearer`.
    if *scheme == b"Bearer" {
        if parts.len() != 2 {
            return Err(AuthFailure::BearerHeader);
        }
        let value = String::from_utf8_lossy(parts[1]);
        let token = world
            .tokens
            .get(value.as_ref())
            .filter(|t| t.kind == TokenKind::Jwt);
        let Some(token) = token else {
            return Err(AuthFailure::TokenNotValid("Token is invalid or expired"));
        };
        if token.expired {
            return Err(AuthFailure::TokenNotValid("Token is invalid or expired"));
        }
        if token.blacklisted {
            return Err(AuthFailure::TokenNotValid("Token is blacklisted"));
        }
        let active = world.users.get(&token.user).is_some_and(|u| u.active);
        if !active {
            return Err(AuthFailure::JwtUserInactive);
        }
        return Ok(token.user);
    }
    // 2. Legacy expiring token: `Token`, any case.
    if scheme.eq_ignore_ascii_case(b"token") {
        match parts.len() {
            1 => return Err(AuthFailure::LegacyNoCredentials),
            2 => {}
            _ => return Err(AuthFailure::LegacySpaces),
        }
        let value = String::from_utf8_lossy(parts[1]);
        let token = world
            .tokens
            .get(value.as_ref())
            .filter(|t| t.kind == TokenKind::Legacy);
        let Some(token) = token else {
            return Err(AuthFailure::LegacyInvalid);
        };
        let active = world.users.get(&token.user).is_some_and(|u| u.active);
        if !active {
            return Err(AuthFailure::LegacyUserInactive);
        }
        if token.expired {
            return Err(AuthFailure::LegacyExpired);
        }
        return Ok(token.user);
    }
    Err(AuthFailure::NotProvided)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixture::Fixture;

    fn world() -> World {
        World::from_fixture(&Fixture::default())
    }

    #[test]
    fn schemes_are_tried_in_order_with_their_own_case_rules() {
        let w = world();
        assert_eq!(authenticate(&w, Some(b"Bearer host-token")), Ok(1));
        assert_eq!(authenticate(&w, Some(b"  Bearer\thost-token ")), Ok(1));
        assert_eq!(
            authenticate(&w, Some(b"bearer host-token")),
            Err(AuthFailure::NotProvided)
        );
        assert_eq!(authenticate(&w, Some(b"TOKEN host-legacy-token")), Ok(1));
        assert_eq!(
            authenticate(&w, Some(b"Token host-token")),
            Err(AuthFailure::LegacyInvalid)
        );
        assert_eq!(
            authenticate(&w, Some(b"Bearer host-legacy-token")),
            Err(AuthFailure::TokenNotValid("Token is invalid or expired"))
        );
        assert_eq!(
            authenticate(&w, Some(b"Bearer")),
            Err(AuthFailure::BearerHeader)
        );
        assert_eq!(
            authenticate(&w, Some(b"Bearer a b")),
            Err(AuthFailure::BearerHeader)
        );
        assert_eq!(
            authenticate(&w, Some(b"Token")),
            Err(AuthFailure::LegacyNoCredentials)
        );
        assert_eq!(
            authenticate(&w, Some(b"Token a b")),
            Err(AuthFailure::LegacySpaces)
        );
        assert_eq!(
            authenticate(&w, Some(b"Bearer blacklisted-token")),
            Err(AuthFailure::TokenNotValid("Token is blacklisted"))
        );
        assert_eq!(
            authenticate(&w, Some(b"Token expired-legacy-token")),
            Err(AuthFailure::LegacyExpired)
        );
        assert_eq!(
            authenticate(&w, Some(b"Bearer inactive-token")),
            Err(AuthFailure::JwtUserInactive)
        );
        assert_eq!(authenticate(&w, None), Err(AuthFailure::NotProvided));
        assert_eq!(authenticate(&w, Some(b"")), Err(AuthFailure::NotProvided));
    }
}
