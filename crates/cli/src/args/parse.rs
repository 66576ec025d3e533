//! Value parsers for command-line options: one grammar per kind of value, shared by every command.
//!
//! Each parser has clap's value-parser shape (`fn(&str) -> Result<T, String>`): clap puts the option and the
//! rejected value in front of the message ("invalid value '-64' for '--size <WxH>': ..."), so a message
//! here says only what is wrong and what would be accepted. Options whose values may start with '-' are
//! declared with `allow_negative_numbers` / `allow_hyphen_values`, so a negative number reaches these
//! parsers instead of being taken for an unknown flag.

use std::str::FromStr;

/// The largest width or height `--size` accepts.
pub const MAX_SIDE: u32 = 16384;

/// The accepted colour forms, for help texts and error messages.
pub const COLOUR_FORMS: &str =
    "a name (black, white, grey/gray, red, green, blue, yellow, cyan, magenta), \
#rrggbb, or r,g,b with each component from 0 to 1";

/// The named colours of [`parse_colour`].
const NAMED_COLOURS: [(&str, [f32; 3]); 10] = [
    ("black", [0.0, 0.0, 0.0]),
    ("white", [1.0, 1.0, 1.0]),
    ("grey", [0.5, 0.5, 0.5]),
    ("gray", [0.5, 0.5, 0.5]),
    ("red", [1.0, 0.0, 0.0]),
    ("green", [0.0, 1.0, 0.0]),
    ("blue", [0.0, 0.0, 1.0]),
    ("yellow", [1.0, 1.0, 0.0]),
    ("cyan", [0.0, 1.0, 1.0]),
    ("magenta", [1.0, 0.0, 1.0]),
];

/// An image size: `N` for NxN or `WxH` (`x` or `X`), each side from 1 to [`MAX_SIDE`].
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let side = |v: &str| -> Result<u32, String> {
        let v = v.trim();
        if let Ok(n) = v.parse::<i64>() {
            if n < 1 || n > MAX_SIDE as i64 {
                return Err(format!(
                    "width and height must be positive and at most {MAX_SIDE} \
                     (N or WxH, e.g. 512 or 640x480)"
                ));
            }
            return Ok(n as u32);
        }
        Err(format!(
            "'{v}' is not a whole number (expected N or WxH, e.g. 512 or 640x480)"
        ))
    };
    match s.split_once(['x', 'X']) {
        Some((w, h)) => Ok((side(w)?, side(h)?)),
        None => side(s).map(|n| (n, n)),
    }
}

/// A colour as linear RGB in [0, 1]: one of the names of [`COLOUR_FORMS`], `#rrggbb`, or `r,g,b` with each
/// component from 0 to 1. Names and hex digits are case-insensitive; spaces around parts are ignored.
pub fn parse_colour(s: &str) -> Result<[f32; 3], String> {
    let t = s.trim();
    let lower = t.to_ascii_lowercase();
    if let Some((_, rgb)) = NAMED_COLOURS.iter().find(|(name, _)| *name == lower) {
        return Ok(*rgb);
    }
    if let Some(hex) = t.strip_prefix('#') {
        let bytes = (hex.len() == 6 && hex.is_ascii())
            .then(|| {
                (0..3)
                    .map(|i| u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).ok())
                    .collect::<Option<Vec<u8>>>()
            })
            .flatten();
        return match bytes.as_deref() {
            Some([r, g, b]) => Ok([*r, *g, *b].map(|c| c as f32 / 255.0)),
            _ => Err(format!(
                "'{t}' is not #rrggbb (six hex digits); expected {COLOUR_FORMS}"
            )),
        };
    }
    let parts: Vec<&str> = t.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        let what = if parts.len() == 1 {
            format!("unknown colour '{t}'")
        } else {
            format!("{} components instead of 3", parts.len())
        };
        return Err(format!("{what}; expected {COLOUR_FORMS}"));
    }
    let mut rgb = [0.0f32; 3];
    for (c, p) in rgb.iter_mut().zip(&parts) {
        *c = match p.parse::<f32>() {
            Ok(v) if (0.0..=1.0).contains(&v) => v,
            Ok(_) => {
                return Err(format!(
                    "component {p} is outside 0 to 1; expected {COLOUR_FORMS}"
                ))
            }
            Err(_) => {
                return Err(format!(
                    "component '{p}' is not a number; expected {COLOUR_FORMS}"
                ))
            }
        };
    }
    Ok(rgb)
}

/// A whole number of at least 1 (steps, views, iterations). Negative values say "must be positive" rather
/// than failing as text.
pub fn positive<T: TryFrom<i128>>(s: &str) -> Result<T, String> {
    whole_from(s, 1, "must be positive", "a whole number, 1 or more")
}

/// A whole number of at least 0 (counts where 0 means "none" or "all", seeds).
pub fn whole<T: TryFrom<i128>>(s: &str) -> Result<T, String> {
    whole_from(s, 0, "must not be negative", "a whole number, 0 or more")
}

/// A whole number of at least `min` that fits `T`; `too_small` says what is wrong with a smaller one,
/// `accepted` what is accepted.
fn whole_from<T: TryFrom<i128>>(
    s: &str,
    min: i128,
    too_small: &str,
    accepted: &str,
) -> Result<T, String> {
    match s.trim().parse::<i128>() {
        Ok(n) if n >= min => T::try_from(n).map_err(|_| format!("too large ({accepted})")),
        Ok(_) => Err(format!("{too_small} ({accepted})")),
        Err(_) => Err(format!("not a whole number (expected {accepted})")),
    }
}

/// A fraction: a number from 0 to 1, both included.
pub fn fraction<T>(s: &str) -> Result<T, String>
where
    T: FromStr + Into<f64> + Copy,
{
    let v: T = finite(s)?;
    if (0.0..=1.0).contains(&v.into()) {
        Ok(v)
    } else {
        Err("must be between 0 and 1".into())
    }
}

/// A finite number (no NaN or infinity); range checks that depend on other options stay with the command.
pub fn finite<T>(s: &str) -> Result<T, String>
where
    T: FromStr + Into<f64> + Copy,
{
    match s.trim().parse::<T>() {
        Ok(v) if v.into().is_finite() => Ok(v),
        Ok(_) => Err("must be a finite number".into()),
        Err(_) => Err("must be a number".into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_size("512"), Ok((512, 512)));
        assert_eq!(parse_size("640x384"), Ok((640, 384)));
        assert_eq!(parse_size("64X48"), Ok((64, 48)));
        assert_eq!(parse_size(" 32 "), Ok((32, 32)));
        assert_eq!(parse_size("16384"), Ok((16384, 16384)));
        for bad in ["0", "0x5", "abc", "axb", "16385", "64x", "", "1.5"] {
            assert!(parse_size(bad).is_err(), "{bad}");
        }
        let neg = parse_size("-64").unwrap_err();
        assert!(neg.contains("must be positive"), "{neg}");
        assert!(parse_size("64x-2").unwrap_err().contains("positive"));
    }

    #[test]
    fn colour_names_hex_and_triples_parse() {
        assert_eq!(parse_colour("white"), Ok([1.0; 3]));
        assert_eq!(parse_colour("Black"), Ok([0.0; 3]));
        assert_eq!(parse_colour(" grey "), Ok([0.5; 3]));
        assert_eq!(parse_colour("GRAY"), Ok([0.5; 3]));
        assert_eq!(parse_colour("red"), Ok([1.0, 0.0, 0.0]));
        assert_eq!(parse_colour("green"), Ok([0.0, 1.0, 0.0]));
        assert_eq!(parse_colour("blue"), Ok([0.0, 0.0, 1.0]));
        assert_eq!(parse_colour("#ff0080"), Ok([1.0, 0.0, 128.0 / 255.0]));
        assert_eq!(parse_colour("#FFFFFF"), Ok([1.0; 3]));
        assert_eq!(parse_colour("0.5,0,1"), Ok([0.5, 0.0, 1.0]));
        assert_eq!(parse_colour("1, 0.5,0"), Ok([1.0, 0.5, 0.0]));
        assert_eq!(parse_colour("0,0,0"), Ok([0.0; 3]));
    }

    #[test]
    fn bad_colours_name_the_accepted_forms() {
        for bad in [
            "purple", "2,0,0", "-1,0,0", "1,1", "1,1,1,1", "a,b,c", "#12345", "#gggggg", "#1234é",
            "", "nan,0,0", "inf,0,0",
        ] {
            let err = parse_colour(bad).expect_err(bad);
            assert!(
                err.contains("#rrggbb") && err.contains("r,g,b"),
                "{bad}: {err}"
            );
        }
        assert!(parse_colour("purple")
            .unwrap_err()
            .contains("unknown colour 'purple'"));
        assert!(parse_colour("2,0,0")
            .unwrap_err()
            .contains("outside 0 to 1"));
    }

    #[test]
    fn numbers_parse_with_clear_limits() {
        assert_eq!(positive::<usize>("3"), Ok(3));
        assert!(positive::<usize>("0")
            .unwrap_err()
            .contains("must be positive"));
        assert!(positive::<u64>("-1")
            .unwrap_err()
            .contains("must be positive"));
        assert!(positive::<u32>("x")
            .unwrap_err()
            .contains("not a whole number"));
        assert!(whole::<usize>("--no-ccm")
            .unwrap_err()
            .contains("not a whole number"));
        assert!(whole::<u32>("1.5").unwrap_err().contains("a whole number"));
        assert!(positive::<u8>("300").unwrap_err().contains("too large"));
        assert_eq!(whole::<u64>("0"), Ok(0));
        assert!(whole::<u64>("-5")
            .unwrap_err()
            .contains("must not be negative"));
        assert_eq!(fraction::<f64>("0.25"), Ok(0.25));
        assert_eq!(fraction::<f64>("1"), Ok(1.0));
        assert!(fraction::<f64>("1.5")
            .unwrap_err()
            .contains("between 0 and 1"));
        assert!(fraction::<f32>("-0.1")
            .unwrap_err()
            .contains("between 0 and 1"));
        assert!(fraction::<f64>("NaN").is_err());
        assert_eq!(finite::<f32>("-2.5"), Ok(-2.5));
        assert!(finite::<f64>("inf").unwrap_err().contains("finite"));
        assert!(finite::<f64>("two")
            .unwrap_err()
            .contains("must be a number"));
    }
}
