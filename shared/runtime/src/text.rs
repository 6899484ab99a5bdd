//! Text for people: error lines that stay readable whatever number the user typed.

use std::borrow::Cow;

/// A number written with more digits than this is rewritten in exponent form. No identifier
/// that an error line names is that long: a `u64` (seed, sample index) has at most 20
/// digits and a bus id at most 24 characters, so only an out-of-range float is touched.
const MAX_DIGITS: usize = 24;

/// A number as written in a text: a run of digits with an optional fraction and an optional
/// `-` before it, that does not follow a letter, a digit, `_` or `.`.
#[derive(Debug)]
pub struct Number<'a> {
    /// The number as written, its sign included.
    pub written: &'a str,
    /// Its digits, the fraction's included.
    pub digits: usize,
    /// The digits after its decimal point.
    pub decimals: usize,
    /// The byte before it (before its sign), if any.
    pub before: Option<u8>,
    /// The byte after it, if any (`e` in `1.5e-3`: a number in exponent form).
    pub after: Option<u8>,
}

/// `text` with each number that `rewrite` gives a replacement for replaced by it; the text
/// itself, borrowed, when it gave none.
pub fn rewrite_numbers<'a>(
    text: &'a str,
    mut rewrite: impl FnMut(&Number) -> Option<String>,
) -> Cow<'a, str> {
    let b = text.as_bytes();
    let word = |c: u8| c.is_ascii_alphanumeric() || c == b'_';
    let mut out = String::new();
    let (mut done, mut i, mut rewritten) = (0, 0, false);
    while i < b.len() {
        if !b[i].is_ascii_digit() || (i > 0 && (word(b[i - 1]) || b[i - 1] == b'.')) {
            i += 1;
            continue;
        }
        let start = if i > 0 && b[i - 1] == b'-' { i - 1 } else { i };
        let mut end = i;
        while end < b.len() && b[end].is_ascii_digit() {
            end += 1;
        }
        let mut decimals = 0;
        if end + 1 < b.len() && b[end] == b'.' && b[end + 1].is_ascii_digit() {
            end += 1;
            while end < b.len() && b[end].is_ascii_digit() {
                end += 1;
                decimals += 1;
            }
        }
        let number = Number {
            written: &text[start..end],
            digits: b[i..end].iter().filter(|c| c.is_ascii_digit()).count(),
            decimals,
            before: start.checked_sub(1).map(|j| b[j]),
            after: b.get(end).copied(),
        };
        if let Some(r) = rewrite(&number) {
            out.push_str(&text[done..start]);
            out.push_str(&r);
            (done, rewritten) = (end, true);
        }
        i = end;
    }
    if !rewritten {
        return Cow::Borrowed(text);
    }
    out.push_str(&text[done..]);
    Cow::Owned(out)
}

/// Rewrites every number in `text` that is written with more than 24 digits in exponent
/// form: `duration_s = 1000…000 must be in (0, 3600]` (Rust prints `1e300` as 301 digits,
/// and serde's "invalid type: floating point" does the same) becomes `duration_s = 1e300
/// must be in (0, 3600]`. A number is as [`rewrite_numbers`] finds it, not followed by a
/// letter, a digit or `_`; its value is kept (`f64`'s shortest exact form). A number that is
/// a whole value in single quotes ('…', what the user typed) is kept. A number beyond `f64`
/// is written as its first six digits and its length. Text without such a number is
/// returned as it is.
pub fn readable_numbers(text: &str) -> Cow<'_, str> {
    let word = |c: Option<u8>| c.is_some_and(|c| c.is_ascii_alphanumeric() || c == b'_');
    rewrite_numbers(text, |n| {
        // A whole value in single quotes is text the user typed (a bus id, a flag's value):
        // quoted as typed.
        let quoted = n.before == Some(b'\'') && n.after == Some(b'\'');
        if n.digits <= MAX_DIGITS || word(n.after) || quoted {
            return None;
        }
        let x = n.written.parse::<f64>().ok()?;
        Some(if x.is_finite() {
            format!("{x:e}")
        } else {
            // Beyond f64 (about 1.8e308): its first digits and how many there are.
            let sign = usize::from(n.written.starts_with('-'));
            format!(
                "{}…({} digits)",
                &n.written[..(sign + 6).min(n.written.len())],
                n.digits
            )
        })
    })
}

/// An error and its causes on one line (`{e:#}`), its numbers readable: what every error line
/// of drivelab and its stage hosts prints, and what a campaign records for a run that failed.
pub fn error_text(e: &anyhow::Error) -> String {
    shortened(
        one_line(&readable_numbers(&format!("{e:#}"))),
        ERROR_LINE_MAX_CHARS,
    )
}

/// The longest error line drivelab prints, in characters: an input that echoes a huge value
/// (a megabyte-long name) is cut in the middle, so the line still names the field and the rule.
pub const ERROR_LINE_MAX_CHARS: usize = 1000;

/// `text` itself when it has at most `max` characters; otherwise its first and last
/// characters with how many were cut between them.
pub fn shortened(text: String, max: usize) -> String {
    let n = text.chars().count();
    if n <= max {
        return text;
    }
    let (head, tail) = (max * 2 / 3, max / 3);
    let start: String = text.chars().take(head).collect();
    let end: String = text.chars().skip(n - tail).collect();
    format!("{start} …({} characters cut)… {end}", n - head - tail)
}

/// `text`'s non-empty lines, trimmed, joined by spaces (a source's multi-line message, such as
/// a parser's caret diagram, on one line).
pub fn one_line(text: &str) -> String {
    join_lines(text, " ")
}

/// The non-empty lines of `text`, trimmed, joined with `sep` (e.g. " / " where the lines
/// are separate messages, such as a child's stderr).
pub fn join_lines(text: &str, sep: &str) -> String {
    let lines: Vec<&str> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect();
    lines.join(sep)
}

#[cfg(test)]
mod tests {
    use super::{readable_numbers, shortened};

    #[test]
    fn a_long_line_is_cut_in_the_middle_and_says_how_much() {
        assert_eq!(shortened("short".into(), 10), "short");
        let long = format!("name = \"{}\" must be 1..=64 characters", "é".repeat(5000));
        let s = shortened(long.clone(), 90);
        assert!(s.starts_with("name = \"ééé"), "{s}");
        assert!(s.ends_with("ééé\" must be 1..=64 characters"), "{s}");
        let cut = long.chars().count() - 60 - 30;
        assert!(s.contains(&format!(" …({cut} characters cut)… ")), "{s}");
    }

    #[test]
    fn a_huge_or_tiny_float_is_written_with_an_exponent_and_keeps_its_value() {
        let huge = format!("duration_s = {} must be in (0, 3600]", 1e300);
        assert!(huge.len() > 300);
        assert_eq!(
            readable_numbers(&huge),
            "duration_s = 1e300 must be in (0, 3600]"
        );
        let line = format!("v = {} and {} V, f = {} Hz", -2.5e40, 1.25e-30, 3e30);
        assert_eq!(
            readable_numbers(&line),
            "v = -2.5e40 and 1.25e-30 V, f = 3e30 Hz"
        );
        let serde = format!("invalid type: floating point `{}`, expected u64", 1e300);
        assert_eq!(
            readable_numbers(&serde),
            "invalid type: floating point `1e300`, expected u64"
        );
    }

    #[test]
    fn a_number_beyond_every_float_says_how_many_digits_it_has() {
        let line = format!("expectation 'crashes <= {}': limit", "9".repeat(400));
        assert_eq!(
            readable_numbers(&line),
            "expectation 'crashes <= 999999…(400 digits)': limit"
        );
        let neg = format!("x = -{} V", "12".repeat(200));
        assert_eq!(readable_numbers(&neg), "x = -121212…(400 digits) V");
    }

    #[test]
    fn ordinary_numbers_identifiers_and_words_are_left_alone() {
        for s in [
            "duration_s = 2.5 must be in (0, 3600]",
            "seed 18446744073709551615 and sample 199999999",
            "bus 999999999999999999999999 is in use",
            "bus ab1000000000000000000000000 and x_1000000000000000000000000",
            "1000000000000000000000000abc",
            "bus id '1234567890123456789012345' must be 1-24 characters",
            "no digits at all",
        ] {
            assert!(
                matches!(readable_numbers(s), std::borrow::Cow::Borrowed(_)),
                "{s}"
            );
        }
        // 25 digits is past every identifier: rewritten.
        assert_eq!(
            readable_numbers("t = 1000000000000000000000000 s"),
            "t = 1e24 s"
        );
    }
}
