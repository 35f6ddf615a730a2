//! Participant text made fit to show: the tail of a log for EvalAI's `stderr`, text safe on a
//! terminal, a start cut at a character boundary.
//!
//! The log is written by the participant's code (untrusted): terminal escapes, control and
//! bidirectional characters are removed so it cannot forge lines or reorder text on the
//! participant's page. EvalAI's own code-upload worker likewise shows the tail of the
//! submission's output when it fails.

/// What a participant sees at most of their agent's output.
pub const MAX_TAIL_CHARS: usize = 10_000;

/// The last `max_chars` characters of `log` worth showing: ANSI escape sequences, control
/// characters (but newlines and tabs), bidirectional and zero-width format characters
/// removed; a tail that starts mid-line starts at the next line.
pub fn participant_tail(log: &[u8], max_chars: usize) -> String {
    let text = String::from_utf8_lossy(log);
    let clean = strip(&text);
    let total = clean.chars().count();
    if total <= max_chars {
        return clean.trim_end().to_owned();
    }
    let start = clean
        .char_indices()
        .nth(total - max_chars)
        .map_or(0, |(i, _)| i);
    let tail = &clean[start..];
    // NB: drop the partial first line, unless the tail is one long line.
    let tail = match tail.find('\n') {
        Some(i) if i + 1 < tail.len() => &tail[i + 1..],
        _ => tail,
    };
    tail.trim_end().to_owned()
}

/// `text` without terminal escapes, control characters (but newlines and tabs) and
/// bidirectional or zero-width format characters: safe to print on an operator's terminal.
pub fn printable(text: &str) -> String {
    strip(text)
}

fn strip(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut chars = text.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '\u{1b}' => skip_escape(&mut chars),
            '\n' | '\t' => out.push(c),
            // A carriage return redraws a line (progress bars): keep what replaced it.
            '\r' if chars.peek() != Some(&'\n') => {
                let line_start = out.rfind('\n').map_or(0, |i| i + 1);
                out.truncate(line_start);
            }
            c if c.is_control() || is_invisible_format(c) => {}
            c => out.push(c),
        }
    }
    out
}

/// `ESC [ ... final`, `ESC ] ... BEL|ESC \`, or `ESC x`.
fn skip_escape(chars: &mut std::iter::Peekable<std::str::Chars<'_>>) {
    match chars.next() {
        Some('[') => {
            for c in chars.by_ref() {
                if ('\u{40}'..='\u{7e}').contains(&c) {
                    break;
                }
            }
        }
        Some(']') => {
            while let Some(c) = chars.next() {
                if c == '\u{7}' || (c == '\u{1b}' && chars.next_if_eq(&'\\').is_some()) {
                    break;
                }
            }
        }
        _ => {}
    }
}

/// The longest start of `text` that fits in `max_bytes` without splitting a character.
pub fn head(text: &str, max_bytes: usize) -> &str {
    let mut end = max_bytes.min(text.len());
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    &text[..end]
}

/// `text` as it is when it fits in `max_bytes`; else its start, ending with `note()`, in
/// `max_bytes` altogether (the note is built only when needed).
pub fn cut_with_note(
    text: &str,
    max_bytes: usize,
    note: impl FnOnce() -> String,
) -> std::borrow::Cow<'_, str> {
    if text.len() <= max_bytes {
        return std::borrow::Cow::Borrowed(text);
    }
    let note = note();
    let kept = head(text, max_bytes.saturating_sub(note.len()));
    std::borrow::Cow::Owned(format!("{kept}{note}"))
}

/// A character a terminal shows as nothing, or as a line break, yet which can reorder, hide or
/// fake what is shown: by Unicode property, not a hand list, so every such character of the
/// Unicode version compiled in counts. Default_Ignorable_Code_Point (zero-width characters,
/// bidirectional controls, tag characters, Hangul fillers, variation selectors, U+034F,
/// U+00AD, U+180E, ...), and the general categories Cf (format), Zl and Zp (U+2028, U+2029).
pub fn is_invisible_format(c: char) -> bool {
    use icu_properties::props::{DefaultIgnorableCodePoint, GeneralCategory};
    use icu_properties::{CodePointMapData, CodePointSetData};
    if c.is_ascii() {
        return false;
    }
    CodePointSetData::new::<DefaultIgnorableCodePoint>().contains(c)
        || matches!(
            CodePointMapData::<GeneralCategory>::new().get(c),
            GeneralCategory::Format
                | GeneralCategory::LineSeparator
                | GeneralCategory::ParagraphSeparator
        )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn invisible_characters_are_found_by_property_and_visible_ones_kept() {
        let invisible = [
            '\u{200b}',
            '\u{200f}',
            '\u{202e}',
            '\u{2066}',
            '\u{feff}',
            '\u{061c}',
            '\u{e0041}', // a tag character
            '\u{2028}',
            '\u{2029}', // line and paragraph separators
            '\u{3164}',
            '\u{115f}',
            '\u{ffa0}', // Hangul fillers
            '\u{180e}',
            '\u{034f}',
            '\u{00ad}',
            '\u{fe0f}',
            '\u{2064}',
        ];
        for c in invisible {
            assert!(is_invisible_format(c), "U+{:04X} passes", c as u32);
        }
        for c in ['a', ' ', 'é', 'ß', 'Ж', '中', '한', '\u{1f600}', '-', '_'] {
            assert!(!is_invisible_format(c), "U+{:04X} is visible", c as u32);
        }
        assert_eq!(
            printable("Team\u{e0041}\u{2028}One\u{3164}\u{ad}"),
            "TeamOne"
        );
    }

    #[test]
    fn a_cut_keeps_the_start_and_the_note_within_the_bound() {
        assert_eq!(cut_with_note("short", 5, || unreachable!()), "short");
        let cut = cut_with_note("ééééé", 7, || "[.]".into());
        assert_eq!(cut, "éé[.]");
        assert!(cut.len() <= 7);
    }

    #[test]
    fn a_head_never_splits_a_character() {
        assert_eq!(head("héllo", 2), "h");
        assert_eq!(head("héllo", 3), "hé");
        assert_eq!(head("hi", 10), "hi");
    }

    #[test]
    fn a_short_log_is_kept_whole_without_its_escapes() {
        let log =
            b"\x1b[1m========= Preparing RouteScenario_0 =========\x1b[0m\nTraceback:\n  boom\n";
        assert_eq!(
            participant_tail(log, MAX_TAIL_CHARS),
            "========= Preparing RouteScenario_0 =========\nTraceback:\n  boom"
        );
    }

    #[test]
    fn a_long_log_keeps_its_last_whole_lines_within_the_limit() {
        let log: String = (0..5000).map(|i| format!("line {i}\n")).collect();
        let tail = participant_tail(log.as_bytes(), 100);
        assert!(tail.chars().count() <= 100);
        assert!(tail.starts_with("line "), "{tail}");
        assert!(tail.ends_with("line 4999"));
    }

    #[test]
    fn control_bidi_and_zero_width_characters_cannot_forge_text() {
        let log = "ok\u{7}\u{0}\u{202e}evil\u{2066}\u{200b}\n\x1b]0;title\x07done\r\nprogress 10%\rprogress 100%\n";
        assert_eq!(
            participant_tail(log.as_bytes(), MAX_TAIL_CHARS),
            "okevil\ndone\nprogress 100%"
        );
    }

    #[test]
    fn invalid_utf8_and_a_multibyte_cut_do_not_panic() {
        let mut log = vec![0xff, 0xfe];
        log.extend("é".repeat(50).as_bytes());
        let tail = participant_tail(&log, 7);
        assert_eq!(tail.chars().count(), 7);
    }
}
