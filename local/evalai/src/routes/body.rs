//! DRF's request parsers: JSON, form-urlencoded and multipart, chosen by `Content-Type`.

use crate::pyjson::{self, Constants, PyValue};

/// `request.data` as a view sees it.
#[derive(Debug, Clone)]
pub(crate) struct Data {
    /// The parsed value (a dict for forms; anything for JSON).
    pub value: PyValue,
    /// Every form/multipart field in order, for `getlist` (None for JSON).
    pub fields: Option<Vec<(String, String)>>,
}

/// Why the body could not be parsed.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum BodyError {
    /// 415 with the request's content type, verbatim.
    Unsupported(String),
    /// 400 with DRF's `ParseError` detail.
    Parse(String),
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    Json,
    Form,
    Multipart,
}

/// DRF's `media_type_matches`: main/sub types case-insensitive, `*` wildcards.
fn parser_for(content_type: &str) -> Option<Kind> {
    let full = content_type
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    let (main, sub) = full.split_once('/').unwrap_or((full.as_str(), ""));
    let matches = |m: &str, s: &str| {
        (main == "*" || main == m) && (sub == "*" || sub == s) && !main.is_empty()
    };
    if matches("application", "json") {
        Some(Kind::Json)
    } else if matches("application", "x-www-form-urlencoded") {
        Some(Kind::Form)
    } else if matches("multipart", "form-data") {
        Some(Kind::Multipart)
    } else {
        None
    }
}

fn is_form_media_type(content_type: &str) -> bool {
    matches!(parser_for(content_type), Some(Kind::Form | Kind::Multipart))
}

/// Python's message for a UTF-8 decoding failure.
fn utf8_error(bytes: &[u8], e: &std::str::Utf8Error) -> String {
    let pos = e.valid_up_to();
    let byte = bytes.get(pos).copied().unwrap_or(0);
    let reason = match e.error_len() {
        None => "unexpected end of data",
        Some(_) if (0x80..0xc2).contains(&byte) || byte >= 0xf5 => "invalid start byte",
        Some(_) => "invalid continuation byte",
    };
    format!("'utf-8' codec can't decode byte 0x{byte:02x} in position {pos}: {reason}")
}

/// Parses `request.data` the way DRF does.
pub(crate) fn parse(content_type: Option<&str>, bytes: &[u8]) -> Result<Data, BodyError> {
    let ct = content_type.unwrap_or("");
    if bytes.is_empty() {
        let form = is_form_media_type(ct);
        return Ok(Data {
            value: PyValue::Dict(Vec::new()),
            fields: form.then(Vec::new),
        });
    }
    match parser_for(ct) {
        Some(Kind::Json) => {
            let text = std::str::from_utf8(bytes).map_err(|e| {
                BodyError::Parse(format!("JSON parse error - {}", utf8_error(bytes, &e)))
            })?;
            let value = pyjson::loads(text, Constants::Reject)
                .map_err(|m| BodyError::Parse(format!("JSON parse error - {m}")))?;
            Ok(Data {
                value,
                fields: None,
            })
        }
        Some(Kind::Form) => Ok(fields_to_data(parse_urlencoded(bytes))),
        Some(Kind::Multipart) => parse_multipart(ct, bytes).map(fields_to_data),
        None => Err(BodyError::Unsupported(ct.to_owned())),
    }
}

fn fields_to_data(fields: Vec<(String, String)>) -> Data {
    let mut dict = Vec::new();
    for (k, v) in &fields {
        // QueryDict.get returns the last value of a repeated key.
        PyValue::dict_set(&mut dict, k.clone(), PyValue::Str(v.clone()));
    }
    Data {
        value: PyValue::Dict(dict),
        fields: Some(fields),
    }
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'+' => {
                out.push(b' ');
                i += 1;
            }
            b'%' => {
                let hex = b
                    .get(i + 1..i + 3)
                    .and_then(|h| std::str::from_utf8(h).ok());
                match hex.and_then(|h| u8::from_str_radix(h, 16).ok()) {
                    Some(v) => {
                        out.push(v);
                        i += 3;
                    }
                    None => {
                        out.push(b'%');
                        i += 1;
                    }
                }
            }
            c => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// Django's `QueryDict` parsing: `&` or `;` separated, `+` is a space, a bare key is "".
pub(crate) fn parse_urlencoded(bytes: &[u8]) -> Vec<(String, String)> {
    let text = String::from_utf8_lossy(bytes);
    text.split(['&', ';'])
        .filter(|p| !p.is_empty())
        .map(|pair| {
            let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
            (percent_decode(k), percent_decode(v))
        })
        .collect()
}

fn header_param(value: &str, name: &str) -> Option<String> {
    value.split(';').skip(1).find_map(|p| {
        let (k, v) = p.trim().split_once('=')?;
        k.trim()
            .eq_ignore_ascii_case(name)
            .then(|| v.trim().trim_matches('"').to_owned())
    })
}

fn find(haystack: &[u8], needle: &[u8], from: usize) -> Option<usize> {
    if needle.is_empty() || from > haystack.len() {
        return None;
    }
    haystack[from..]
        .windows(needle.len())
        .position(|w| w == needle)
        .map(|p| p + from)
}

/// A small multipart/form-data reader: text fields become values, file parts are skipped.
fn parse_multipart(content_type: &str, bytes: &[u8]) -> Result<Vec<(String, String)>, BodyError> {
    let boundary = header_param(content_type, "boundary").filter(|b| !b.is_empty());
    let Some(boundary) = boundary else {
        return Err(BodyError::Parse(
            "Multipart form parse error - Invalid boundary in multipart: None".to_owned(),
        ));
    };
    let delimiter = format!("--{boundary}").into_bytes();
    let mut fields = Vec::new();
    let Some(mut pos) = find(bytes, &delimiter, 0) else {
        return Err(BodyError::Parse(
            "Multipart form parse error - Multipart body has no boundary".to_owned(),
        ));
    };
    loop {
        let start = pos + delimiter.len();
        if bytes.get(start..start + 2) == Some(b"--") {
            break;
        }
        let Some(next) = find(bytes, &delimiter, start) else {
            break;
        };
        let part = &bytes[start..next];
        let part = part.strip_prefix(b"\r\n").unwrap_or(part);
        let part = part.strip_suffix(b"\r\n").unwrap_or(part);
        if let Some(split) = find(part, b"\r\n\r\n", 0) {
            let head = String::from_utf8_lossy(&part[..split]);
            let content = &part[split + 4..];
            let disposition = head
                .lines()
                .find(|l| l.to_ascii_lowercase().starts_with("content-disposition:"))
                .unwrap_or("");
            let name = header_param(disposition, "name");
            let is_file = header_param(disposition, "filename").is_some();
            if let (Some(name), false) = (name, is_file) {
                fields.push((name, String::from_utf8_lossy(content).into_owned()));
            }
        }
        pos = next;
    }
    Ok(fields)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn form_bodies_keep_the_last_repeated_key_and_decode_escapes() {
        let d = parse(
            Some("application/x-www-form-urlencoded"),
            b"a=1&b=x+y%21&a=2&c&bad=%zz",
        )
        .unwrap();
        assert_eq!(d.value.get("a"), Some(&PyValue::str("2")));
        assert_eq!(d.value.get("b"), Some(&PyValue::str("x y!")));
        assert_eq!(d.value.get("c"), Some(&PyValue::str("")));
        assert_eq!(d.value.get("bad"), Some(&PyValue::str("%zz")));
        assert_eq!(d.fields.unwrap().len(), 5);
    }

    #[test]
    fn content_types_are_matched_like_drf() {
        assert!(parse(Some("Application/JSON; charset=utf-8"), b"{}").is_ok());
        assert_eq!(
            parse(Some("text/plain"), b"x").unwrap_err(),
            BodyError::Unsupported("text/plain".to_owned())
        );
        assert_eq!(
            parse(None, b"x").unwrap_err(),
            BodyError::Unsupported(String::new())
        );
        assert!(
            parse(Some("text/plain"), b"").is_ok(),
            "empty bodies are never parsed"
        );
        assert_eq!(
            parse(Some("application/json"), b"{\"a\": NaN}").unwrap_err(),
            BodyError::Parse(
                "JSON parse error - Out of range float values are not JSON compliant: 'NaN'"
                    .to_owned()
            )
        );
    }

    #[test]
    fn multipart_text_fields_are_read() {
        let body = b"--XX\r\nContent-Disposition: form-data; name=\"submission\"\r\n\r\n1\r\n--XX\r\nContent-Disposition: form-data; name=\"f\"; filename=\"a.txt\"\r\n\r\nfile\r\n--XX--\r\n";
        let d = parse(Some("multipart/form-data; boundary=XX"), body).unwrap();
        assert_eq!(d.value.get("submission"), Some(&PyValue::str("1")));
        assert_eq!(d.value.get("f"), None);
    }
}
