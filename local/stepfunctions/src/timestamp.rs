//! Timestamps as Step Functions reads (RFC 3339, uppercase `T` and `Z`) and writes them.

use time::format_description::well_known::Rfc3339;
use time::macros::format_description;
use time::{OffsetDateTime, UtcOffset};

/// Parses a Choice/Wait timestamp: RFC 3339 with an uppercase `T` between date and time and
/// an uppercase `Z` (or a numeric offset), as the Amazon States Language requires.
pub fn parse(text: &str) -> Option<OffsetDateTime> {
    // NB: the `time` crate also accepts `t` and `z`, which Step Functions refuses.
    if text.as_bytes().get(10) != Some(&b'T') || text.contains(['t', 'z']) {
        return None;
    }
    OffsetDateTime::parse(text, &Rfc3339).ok()
}

/// Formats an instant as Step Functions shows times in the context object
/// (`2019-03-26T20:14:13.192Z`: UTC, milliseconds).
pub fn format(at: OffsetDateTime) -> String {
    let utc = at.to_offset(UtcOffset::UTC);
    utc.format(format_description!(
        "[year]-[month]-[day]T[hour]:[minute]:[second].[subsecond digits:3]Z"
    ))
    .unwrap_or_else(|_| utc.unix_timestamp().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uppercase_t_and_z_are_required() {
        assert!(parse("2016-03-14T01:59:00Z").is_some());
        assert!(parse("2016-03-14T01:59:00.123+02:00").is_some());
        assert!(parse("2016-03-14t01:59:00Z").is_none());
        assert!(parse("2016-03-14T01:59:00z").is_none());
        assert!(parse("2016-03-14 01:59:00Z").is_none());
        assert!(parse("yesterday").is_none());
        assert!(parse("").is_none());
    }

    #[test]
    fn offsets_compare_as_instants() {
        assert_eq!(
            parse("2016-03-14T03:59:00+02:00"),
            parse("2016-03-14T01:59:00Z")
        );
    }

    #[test]
    fn formatted_times_have_milliseconds_and_z() {
        let at = parse("2019-03-26T22:14:13.192456+02:00").unwrap();
        assert_eq!(format(at), "2019-03-26T20:14:13.192Z");
    }
}
