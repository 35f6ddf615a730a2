//! Timestamps as Django/DRF read and write them.

use time::{Date, Month, OffsetDateTime, PrimitiveDateTime, Time, UtcOffset};

/// Now, truncated to microseconds as Postgres stores it.
pub fn now() -> OffsetDateTime {
    let t = OffsetDateTime::now_utc();
    let micros = t.microsecond();
    t.replace_microsecond(micros).unwrap_or(t)
}

/// DRF's `DateTimeField` output: ISO-8601 in UTC with `Z`, microseconds only when non-zero.
pub fn format(t: OffsetDateTime) -> String {
    let t = t.to_offset(UtcOffset::UTC);
    let mut out = format!(
        "{:04}-{:02}-{:02}T{:02}:{:02}:{:02}",
        t.year(),
        u8::from(t.month()),
        t.day(),
        t.hour(),
        t.minute(),
        t.second()
    );
    if t.microsecond() != 0 {
        out.push_str(&format!(".{:06}", t.microsecond()));
    }
    out.push('Z');
    out
}

/// Microseconds from a fraction's digits (`5` is 500,000; digits past the sixth are cut).
fn micros(digits: &str) -> Option<u32> {
    if digits.is_empty() {
        return None;
    }
    let six: String = digits.chars().chain("000000".chars()).take(6).collect();
    six.parse().ok()
}

/// Django's `parse_datetime`: `YYYY-MM-DD[T ]HH:MM[:SS[.ffffff]][Z|±HH[:MM]]`.
/// A naive value is taken as UTC (EvalAI's `TIME_ZONE`).
pub fn parse(s: &str) -> Option<OffsetDateTime> {
    let b = s.as_bytes();
    let mut i = 0;
    let num = |min: usize, max: usize, i: &mut usize| -> Option<u32> {
        let start = *i;
        while *i < b.len() && *i - start < max && b[*i].is_ascii_digit() {
            *i += 1;
        }
        if *i - start < min {
            return None;
        }
        s[start..*i].parse().ok()
    };
    let expect = |c: &[u8], i: &mut usize| -> Option<()> {
        if *i < b.len() && c.contains(&b[*i]) {
            *i += 1;
            Some(())
        } else {
            None
        }
    };
    let year = num(4, 4, &mut i)?;
    expect(b"-", &mut i)?;
    let month = num(1, 2, &mut i)?;
    expect(b"-", &mut i)?;
    let day = num(1, 2, &mut i)?;
    expect(b"T ", &mut i)?;
    let hour = num(1, 2, &mut i)?;
    expect(b":", &mut i)?;
    let minute = num(1, 2, &mut i)?;
    let mut second = 0;
    let mut micro = 0;
    if expect(b":", &mut i).is_some() {
        second = num(1, 2, &mut i)?;
        if expect(b".,", &mut i).is_some() {
            let start = i;
            while i < b.len() && b[i].is_ascii_digit() && i - start < 12 {
                i += 1;
            }
            micro = micros(&s[start..i])?;
        }
    }
    let offset = if i == b.len() {
        UtcOffset::UTC
    } else if b[i] == b'Z' {
        i += 1;
        UtcOffset::UTC
    } else if b[i] == b'+' || b[i] == b'-' {
        let neg = b[i] == b'-';
        i += 1;
        let h = num(2, 2, &mut i)?;
        let _ = expect(b":", &mut i);
        let m = if i < b.len() { num(2, 2, &mut i)? } else { 0 };
        let secs = i32::try_from(h * 3600 + m * 60).ok()?;
        UtcOffset::from_whole_seconds(if neg { -secs } else { secs }).ok()?
    } else {
        return None;
    };
    if i != b.len() {
        return None;
    }
    let date = Date::from_calendar_date(
        i32::try_from(year).ok()?,
        Month::try_from(u8::try_from(month).ok()?).ok()?,
        u8::try_from(day).ok()?,
    )
    .ok()?;
    let time = Time::from_hms_micro(
        u8::try_from(hour).ok()?,
        u8::try_from(minute).ok()?,
        u8::try_from(second).ok()?,
        micro,
    )
    .ok()?;
    Some(PrimitiveDateTime::new(date, time).assume_offset(offset))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_like_drf() {
        let t = parse("2026-01-02T03:04:05Z").unwrap();
        assert_eq!(format(t), "2026-01-02T03:04:05Z");
        let t = parse("2026-01-02 03:04:05.5+01:00").unwrap();
        assert_eq!(format(t), "2026-01-02T02:04:05.500000Z");
        assert!(parse("2026-01-02").is_none());
        assert!(parse("yesterday").is_none());
        assert!(parse("2026-13-02T00:00").is_none());
    }
}
