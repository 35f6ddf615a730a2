//! Name rules (DNS-1123, label keys and values) with the real messages, and random names and uids.

use std::collections::hash_map::RandomState;
use std::hash::{BuildHasher, Hasher};
use std::sync::atomic::{AtomicU64, Ordering};

const SUBDOMAIN_MSG: &str = "a lowercase RFC 1123 subdomain must consist of lower case alphanumeric characters, '-' or '.', and must start and end with an alphanumeric character (e.g. 'example.com', regex used for validation is '[a-z0-9]([-a-z0-9]*[a-z0-9])?(\\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*')";
const LABEL_MSG: &str = "a lowercase RFC 1123 label must consist of lower case alphanumeric characters or '-', and must start and end with an alphanumeric character (e.g. 'my-name',  or '123-abc', regex used for validation is '[a-z0-9]([-a-z0-9]*[a-z0-9])?')";
const LABEL_VALUE_MSG: &str = "a valid label must be an empty string or consist of alphanumeric characters, '-', '_' or '.', and must start and end with an alphanumeric character (e.g. 'MyValue',  or 'my_value',  or '12345', regex used for validation is '(([A-Za-z0-9][-A-Za-z0-9_.]*)?[A-Za-z0-9])?')";
const QUALIFIED_NAME_MSG: &str = "name part must consist of alphanumeric characters, '-', '_' or '.', and must start and end with an alphanumeric character (e.g. 'MyName',  or 'my.name',  or '123-abc', regex used for validation is '([A-Za-z0-9][-A-Za-z0-9_.]*)?[A-Za-z0-9]')";

/// Longest DNS-1123 label (and label value, and label name part).
pub const LABEL_MAX: usize = 63;
/// Longest DNS-1123 subdomain.
pub const SUBDOMAIN_MAX: usize = 253;

fn max_len(n: usize) -> String {
    format!("must be no more than {n} bytes")
}

fn is_label(s: &str) -> bool {
    let b = s.as_bytes();
    !b.is_empty()
        && b.iter()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == b'-')
        && b[0] != b'-'
        && b[b.len() - 1] != b'-'
}

/// Messages for a name that is not a DNS-1123 label (empty when valid).
pub fn dns1123_label_errors(s: &str) -> Vec<String> {
    let mut errs = Vec::new();
    if s.len() > LABEL_MAX {
        errs.push(max_len(LABEL_MAX));
    }
    if !is_label(s) {
        errs.push(LABEL_MSG.to_owned());
    }
    errs
}

/// Messages for a name that is not a DNS-1123 subdomain (empty when valid).
pub fn dns1123_subdomain_errors(s: &str) -> Vec<String> {
    let mut errs = Vec::new();
    if s.len() > SUBDOMAIN_MAX {
        errs.push(max_len(SUBDOMAIN_MAX));
    }
    if s.is_empty() || !s.split('.').all(is_label) {
        errs.push(SUBDOMAIN_MSG.to_owned());
    }
    errs
}

fn is_label_value_body(s: &str) -> bool {
    let b = s.as_bytes();
    b.iter()
        .all(|c| c.is_ascii_alphanumeric() || matches!(c, b'-' | b'_' | b'.'))
        && b.first().is_some_and(u8::is_ascii_alphanumeric)
        && b.last().is_some_and(u8::is_ascii_alphanumeric)
}

/// Messages for an invalid label value (empty when valid; the empty value is valid).
pub fn label_value_errors(v: &str) -> Vec<String> {
    let mut errs = Vec::new();
    if v.len() > LABEL_MAX {
        errs.push(max_len(LABEL_MAX));
    }
    if !v.is_empty() && !is_label_value_body(v) {
        errs.push(LABEL_VALUE_MSG.to_owned());
    }
    errs
}

/// Messages for an invalid label or annotation key (`[prefix/]name`).
pub fn qualified_name_errors(k: &str) -> Vec<String> {
    let mut errs = Vec::new();
    let (prefix, name) = match k.split_once('/') {
        Some((p, n)) => (Some(p), n),
        None => (None, k),
    };
    if let Some(prefix) = prefix {
        if prefix.is_empty() {
            errs.push("prefix part must be non-empty".to_owned());
        } else {
            for msg in dns1123_subdomain_errors(prefix) {
                errs.push(format!("prefix part {msg}"));
            }
        }
        if name.contains('/') {
            errs.push(format!("a qualified name {QUALIFIED_NAME_MSG}"));
            return errs;
        }
    }
    if name.is_empty() {
        errs.push("name part must be non-empty".to_owned());
    } else {
        if name.len() > LABEL_MAX {
            errs.push(format!("name part {}", max_len(LABEL_MAX)));
        }
        if !is_label_value_body(name) {
            errs.push(QUALIFIED_NAME_MSG.to_owned());
        }
    }
    errs
}

/// 64 random bits: process-random SipHash keys over a counter and the clock (names, not secrets).
pub fn random_u64() -> u64 {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let mut h = RandomState::new().build_hasher();
    h.write_u64(COUNTER.fetch_add(1, Ordering::Relaxed));
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or_default();
    h.write_u128(nanos);
    h.finish()
}

/// The alphabet of Kubernetes' generated name suffixes (no vowels, no confusable digits).
const SUFFIX_ALPHABET: &[u8] = b"bcdfghjklmnpqrstvwxz2456789";
/// Longest base kept by `generateName` (63 minus the 5-character suffix).
const MAX_GENERATED_BASE: usize = 58;

/// `n` random characters from the alphabet Kubernetes uses for generated names.
pub fn random_suffix(n: usize) -> String {
    let mut out = String::with_capacity(n);
    let mut bits = random_u64();
    for i in 0..n {
        if i % 8 == 7 {
            bits = random_u64();
        }
        let idx = (bits % SUFFIX_ALPHABET.len() as u64) as usize;
        bits /= SUFFIX_ALPHABET.len() as u64;
        out.push(char::from(SUFFIX_ALPHABET[idx]));
    }
    out
}

/// `generateName` semantics: the base cut to 58 characters plus 5 random ones.
pub fn generate_name(base: &str) -> String {
    let mut cut = base.len().min(MAX_GENERATED_BASE);
    while !base.is_char_boundary(cut) {
        cut -= 1;
    }
    format!("{}{}", &base[..cut], random_suffix(5))
}

/// A random (version 4) UUID in the canonical 8-4-4-4-12 form.
pub fn new_uid() -> String {
    let hi = random_u64();
    let lo = random_u64();
    let mut b = [0u8; 16];
    b[..8].copy_from_slice(&hi.to_be_bytes());
    b[8..].copy_from_slice(&lo.to_be_bytes());
    b[6] = (b[6] & 0x0f) | 0x40;
    b[8] = (b[8] & 0x3f) | 0x80;
    let hex: String = b.iter().map(|x| format!("{x:02x}")).collect();
    format!(
        "{}-{}-{}-{}-{}",
        &hex[0..8],
        &hex[8..12],
        &hex[12..16],
        &hex[16..20],
        &hex[20..32]
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subdomains_and_labels_follow_rfc_1123() {
        assert!(dns1123_subdomain_errors("job-1.a").is_empty());
        assert_eq!(dns1123_subdomain_errors("Job_1").len(), 1);
        assert_eq!(dns1123_subdomain_errors("").len(), 1);
        assert_eq!(dns1123_subdomain_errors("a..b").len(), 1);
        assert_eq!(
            dns1123_subdomain_errors(&"a".repeat(254)),
            vec![max_len(253)]
        );
        assert!(dns1123_label_errors("sim-0").is_empty());
        assert_eq!(dns1123_label_errors("a.b").len(), 1);
        assert_eq!(dns1123_label_errors("-a").len(), 1);
        assert_eq!(dns1123_label_errors(&"a".repeat(64)), vec![max_len(63)]);
    }

    #[test]
    fn label_values_and_keys_are_checked_like_the_api_server() {
        assert!(label_value_errors("").is_empty());
        assert!(label_value_errors("My_value.1").is_empty());
        assert_eq!(label_value_errors("a b").len(), 1);
        assert_eq!(label_value_errors(&"a".repeat(64)), vec![max_len(63)]);
        assert!(qualified_name_errors("batch.kubernetes.io/job-name").is_empty());
        assert!(qualified_name_errors("app").is_empty());
        assert_eq!(qualified_name_errors("Bad_Prefix/x").len(), 1);
        assert_eq!(qualified_name_errors("a/b/c").len(), 1);
        assert_eq!(
            qualified_name_errors("/x"),
            vec!["prefix part must be non-empty"]
        );
    }

    #[test]
    fn generated_names_and_uids_have_the_kubernetes_shapes() {
        let s = random_suffix(5);
        assert_eq!(s.len(), 5);
        assert!(s.bytes().all(|c| SUFFIX_ALPHABET.contains(&c)));
        assert_ne!(random_suffix(12), random_suffix(12));
        let long = generate_name(&format!("{}-", "a".repeat(70)));
        assert_eq!(long.len(), 63);
        let uid = new_uid();
        assert_eq!(uid.len(), 36);
        assert_eq!(uid.as_bytes()[14], b'4');
        assert!(matches!(uid.as_bytes()[19], b'8' | b'9' | b'a' | b'b'));
        assert_ne!(new_uid(), uid);
    }
}
