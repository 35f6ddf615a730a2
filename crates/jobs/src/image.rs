//! Container image references, checked against the distribution reference grammar.
//!
//! ```text
//! reference  := name [ ":" tag ] [ "@" digest ]
//! name       := [ domain "/" ] path-component ( "/" path-component )*     (<= 255 chars)
//! domain     := domain-component ( "." domain-component )* [ ":" port ]
//! path-component := [a-z0-9]+ ( ( "." | "_" | "__" | "-"+ ) [a-z0-9]+ )*
//! tag        := [A-Za-z0-9_] [A-Za-z0-9_.-]{0,127}
//! digest     := algorithm ":" hex{32,}   algorithm := [A-Za-z][A-Za-z0-9]* ( [+._-] ... )*
//! ```
//!
//! The participant's image URI comes from EvalAI, so it is untrusted: anything outside the
//! grammar (spaces, newlines, shell or YAML syntax, uppercase paths) is refused here, before
//! it reaches a Job.

use std::fmt;

/// The longest name (domain and path) the grammar allows.
pub const MAX_NAME_LEN: usize = 255;

/// The longest whole reference: a 255-character name, a 128-character tag and a sha512 digest
/// fit, with room to spare.
pub const MAX_REFERENCE_LEN: usize = 1024;

/// A parsed image reference.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ImageRef {
    /// Registry host (and port), when the reference names one.
    pub domain: Option<String>,
    /// Repository path.
    pub path: String,
    /// Tag, if any.
    pub tag: Option<String>,
    /// Digest (`sha256:...`), if any.
    pub digest: Option<String>,
}

impl fmt::Display for ImageRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if let Some(d) = &self.domain {
            write!(f, "{d}/")?;
        }
        f.write_str(&self.path)?;
        if let Some(t) = &self.tag {
            write!(f, ":{t}")?;
        }
        if let Some(d) = &self.digest {
            write!(f, "@{d}")?;
        }
        Ok(())
    }
}

/// An image in Amazon ECR named by its tag: what can be resolved to the digest it names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EcrTagged<'a> {
    /// The registry: its AWS account id.
    pub registry: &'a str,
    /// The registry's region.
    pub region: &'a str,
    /// The repository's name.
    pub repository: &'a str,
    /// The tag.
    pub tag: &'a str,
}

impl ImageRef {
    /// The ECR image this names by tag (`<account>.dkr.ecr[-fips].<region>.amazonaws.com[.cn]/
    /// <repository>:<tag>`); `None` for another registry or a reference that has a digest.
    pub fn ecr_tagged(&self) -> Option<EcrTagged<'_>> {
        if self.digest.is_some() {
            return None;
        }
        let host = self.domain.as_deref()?;
        let host = host
            .strip_suffix(".amazonaws.com")
            .or_else(|| host.strip_suffix(".amazonaws.com.cn"))?;
        let (registry, rest) = host.split_once('.')?;
        let region = rest
            .strip_prefix("dkr.ecr.")
            .or_else(|| rest.strip_prefix("dkr.ecr-fips."))?;
        let account = registry.len() == 12 && registry.bytes().all(|b| b.is_ascii_digit());
        let region_ok = !region.is_empty() && !region.contains('.');
        (account && region_ok).then_some(EcrTagged {
            registry,
            region,
            repository: &self.path,
            tag: self.tag.as_deref().unwrap_or("latest"),
        })
    }

    /// The same image named by `digest` alone: every pull gets exactly these bytes.
    pub fn pinned(&self, digest: &str) -> ImageRef {
        ImageRef {
            tag: None,
            digest: Some(digest.to_owned()),
            ..self.clone()
        }
    }
}

fn alnum_lower(c: u8) -> bool {
    c.is_ascii_lowercase() || c.is_ascii_digit()
}

fn path_component(s: &str) -> bool {
    let b = s.as_bytes();
    if b.is_empty() || !alnum_lower(b[0]) || !alnum_lower(b[b.len() - 1]) {
        return false;
    }
    let mut i = 0;
    while i < b.len() {
        if alnum_lower(b[i]) {
            i += 1;
            continue;
        }
        // A separator run between two alphanumeric runs.
        let start = i;
        while i < b.len() && !alnum_lower(b[i]) {
            i += 1;
        }
        let sep = &s[start..i];
        let ok = sep == "." || sep == "_" || sep == "__" || sep.bytes().all(|c| c == b'-');
        if !ok {
            return false;
        }
    }
    true
}

fn domain_component(s: &str) -> bool {
    let b = s.as_bytes();
    !b.is_empty()
        && b.iter().all(|c| c.is_ascii_alphanumeric() || *c == b'-')
        && b[0].is_ascii_alphanumeric()
        && b[b.len() - 1].is_ascii_alphanumeric()
}

fn domain(s: &str) -> Result<(), String> {
    let (host, port) = match s.rsplit_once(':') {
        Some((h, p)) => (h, Some(p)),
        None => (s, None),
    };
    if host.starts_with('[') {
        return Err("IPv6 registry addresses are not supported".into());
    }
    if !host.split('.').all(domain_component) {
        return Err(format!("`{s}` is not a valid registry host"));
    }
    if let Some(p) = port {
        if p.is_empty() || p.len() > 5 || !p.bytes().all(|c| c.is_ascii_digit()) {
            return Err(format!("`{p}` is not a valid registry port"));
        }
    }
    Ok(())
}

fn tag(s: &str) -> bool {
    let b = s.as_bytes();
    let word = |c: &u8| c.is_ascii_alphanumeric() || *c == b'_';
    !b.is_empty()
        && b.len() <= 128
        && word(&b[0])
        && b.iter().all(|c| word(c) || *c == b'.' || *c == b'-')
}

fn digest(s: &str) -> bool {
    let Some((algorithm, hex)) = s.split_once(':') else {
        return false;
    };
    let algorithm_ok = algorithm.split(['+', '.', '_', '-']).all(|part| {
        let b = part.as_bytes();
        !b.is_empty() && b[0].is_ascii_alphabetic() && b.iter().all(u8::is_ascii_alphanumeric)
    });
    algorithm_ok && hex.len() >= 32 && hex.bytes().all(|c| c.is_ascii_hexdigit())
}

/// Parses and checks an image reference; the error says what is wrong.
pub fn parse_image(reference: &str) -> Result<ImageRef, String> {
    if reference.is_empty() {
        return Err("the image reference is empty".into());
    }
    // Checked first, so no message below can echo an oversized part.
    if reference.len() > MAX_REFERENCE_LEN {
        return Err(format!(
            "the image reference is {} bytes long, over the limit of {MAX_REFERENCE_LEN}",
            reference.len()
        ));
    }
    if let Some(c) = reference
        .chars()
        .find(|c| c.is_whitespace() || c.is_control() || !c.is_ascii())
    {
        return Err(format!(
            "the image reference contains the character {c:?}, which no image reference may hold"
        ));
    }
    let (name_tag, digest_part) = match reference.split_once('@') {
        Some((n, d)) => (n, Some(d)),
        None => (reference, None),
    };
    if let Some(d) = digest_part {
        if !digest(d) {
            return Err(format!(
                "`{d}` is not a digest (`algorithm:hex`, at least 32 hex digits)"
            ));
        }
    }
    let last_slash = name_tag.rfind('/').map(|i| i + 1).unwrap_or(0);
    let (name, tag_part) = match name_tag[last_slash..].rfind(':') {
        Some(i) => (
            &name_tag[..last_slash + i],
            Some(&name_tag[last_slash + i + 1..]),
        ),
        None => (name_tag, None),
    };
    if let Some(t) = tag_part {
        if !tag(t) {
            return Err(format!(
                "`{t}` is not a tag (letters, digits, `_`, `.`, `-`, at most 128, not starting with `.` or `-`)"
            ));
        }
    }
    if name.len() > MAX_NAME_LEN {
        return Err(format!(
            "the repository name is {} characters, over the limit of {MAX_NAME_LEN}",
            name.len()
        ));
    }
    let mut components: Vec<&str> = name.split('/').collect();
    let first = components[0];
    let domain_part = if components.len() > 1
        && (first.contains('.') || first.contains(':') || first == "localhost")
    {
        domain(first)?;
        Some(components.remove(0).to_owned())
    } else {
        None
    };
    for component in &components {
        if !path_component(component) {
            return Err(format!(
                "`{component}` is not a repository path component (lowercase letters and digits separated by `.`, `_`, `__` or `-`)"
            ));
        }
    }
    Ok(ImageRef {
        domain: domain_part,
        path: components.join("/"),
        tag: tag_part.map(str::to_owned),
        digest: digest_part.map(str::to_owned),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn common_references_parse_into_their_parts() {
        let r =
            parse_image("342236305043.dkr.ecr.us-west-2.amazonaws.com/leaderboard-20:carla-0.9.15")
                .unwrap();
        assert_eq!(
            r.domain.as_deref(),
            Some("342236305043.dkr.ecr.us-west-2.amazonaws.com")
        );
        assert_eq!(r.path, "leaderboard-20");
        assert_eq!(r.tag.as_deref(), Some("carla-0.9.15"));
        for ok in [
            "carlasim/carla:0.9.15",
            "ubuntu",
            "localhost:5000/team/agent_v2__final:latest",
            "registry.example.com:443/a/b/c@sha256:0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef",
            "ghcr.io/org/img:v1.2-rc_3@sha256:0123456789abcdef0123456789abcdef",
            "a---b/c.d",
        ] {
            let r = parse_image(ok).unwrap_or_else(|e| panic!("{ok}: {e}"));
            assert_eq!(r.to_string(), ok);
        }
    }

    #[test]
    fn an_ecr_tag_is_what_can_be_pinned_to_its_digest() {
        let digest = format!("sha256:{}", "ab".repeat(32));
        let r = parse_image("342236305043.dkr.ecr.us-west-2.amazonaws.com/team/agent:v3").unwrap();
        let ecr = r.ecr_tagged().unwrap();
        assert_eq!(
            (ecr.registry, ecr.region, ecr.repository, ecr.tag),
            ("342236305043", "us-west-2", "team/agent", "v3")
        );
        assert_eq!(
            r.pinned(&digest).to_string(),
            format!("342236305043.dkr.ecr.us-west-2.amazonaws.com/team/agent@{digest}")
        );
        // No tag is `latest`, as a pull reads it.
        let latest =
            parse_image("342236305043.dkr.ecr-fips.us-gov-west-1.amazonaws.com/a").unwrap();
        assert_eq!(
            latest.ecr_tagged().map(|e| (e.region, e.tag)),
            Some(("us-gov-west-1", "latest"))
        );
        for other in [
            "carlasim/carla:0.9.15",
            "ghcr.io/org/img:v1",
            "12345.dkr.ecr.us-west-2.amazonaws.com/a:v1",
            "342236305043.dkr.ecr.us-west-2.amazonaws.com.evil.io/a:v1",
            "342236305043.dkr.ecr.us-west-2.amazonaws.com/a:v1@sha256:0123456789abcdef0123456789abcdef",
        ] {
            assert_eq!(parse_image(other).unwrap().ecr_tagged(), None, "{other}");
        }
    }

    #[test]
    fn hostile_or_malformed_references_are_refused_with_the_reason() {
        for (bad, needle) in [
            ("", "empty"),
            ("img:latest\nkind: Pod", "character '\\n'"),
            ("img; rm -rf /", "character ' '"),
            (
                "Team/Agent:latest",
                "`Team` is not a repository path component",
            ),
            ("img:-bad", "is not a tag"),
            ("img:", "is not a tag"),
            ("img@sha256:abc", "is not a digest"),
            ("reg.io:99999999/x", "registry port"),
            ("-bad.io/x", "registry host"),
            ("a//b", "`` is not a repository path component"),
            ("a/b/", "`` is not a repository path component"),
            ("a..b", "`a..b` is not"),
            ("a$(whoami)", "`a$(whoami)` is not"),
            ("zoë/agent", "character 'ë'"),
            ("[::1]:5000/x", "IPv6"),
        ] {
            let err = parse_image(bad).expect_err(bad);
            assert!(err.contains(needle), "{bad:?}: {err}");
        }
        let long = format!("{}:t", "a".repeat(300));
        assert!(parse_image(&long).unwrap_err().contains("over the limit"));
        let long_tag = format!("img:{}", "t".repeat(129));
        assert!(parse_image(&long_tag).is_err());
    }
}
