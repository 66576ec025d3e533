//! Captions: a small fixed grammar over a small vocabulary, generated from and parsed back into an
//! [`Appearance`].
//!
//! Grammar (one caption per scene, describing its main object):
//!
//! ```text
//! caption := article colour ["and" colour] [pattern] shape ["on" "a" "table"]
//! article := "a" | "an"              ("an" before a vowel: "an orange cube")
//! ```
//!
//! The second colour is only written with a pattern, and only when it is not the first colour's default
//! partner (white, or black for white things): "a red striped vase" is red and white, "a red and blue
//! striped vase" is red and blue. A solid object is just "a red sphere". So every appearance has exactly
//! one caption, and [`parse_caption`] inverts [`caption`].

use super::palette::ColorName;
use super::pattern::PatternKind;
use super::shape::ShapeKind;
use serde::{Deserialize, Serialize};

/// Every word a caption can contain (the demo tokenizer's vocabulary).
pub const VOCABULARY: &[&str] = &[
    // grammar
    "a",
    "an",
    "and",
    "on", // colours
    "red",
    "green",
    "blue",
    "yellow",
    "white",
    "black",
    "orange",
    "purple",
    "pink",
    "gray",
    "brown",
    // patterns
    "striped",
    "checkered",
    "dotted",
    "gradient", // shapes
    "sphere",
    "cube",
    "cylinder",
    "cone",
    "torus",
    "vase",
    "table",
    "snowman",
    "mushroom",
];

/// What a caption says about a scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Appearance {
    pub shape: ShapeKind,
    /// First and second colour; for solid objects the second is the first's default partner.
    pub colors: [ColorName; 2],
    pub pattern: PatternKind,
    /// The object stands on a table.
    pub on_table: bool,
}

impl Appearance {
    /// Fills the unsaid second colour of solid objects with the default partner, so two appearances that
    /// read the same compare equal.
    pub fn normalized(mut self) -> Self {
        if !self.pattern.uses_second_color() {
            self.colors[1] = self.colors[0].default_partner();
        }
        self
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("caption \"{caption}\": {msg}")]
pub struct CaptionError {
    pub caption: String,
    pub msg: String,
}

/// The one caption of an appearance.
pub fn caption(app: &Appearance) -> String {
    let app = app.normalized();
    let first = app.colors[0].word();
    let article = if first.starts_with(['a', 'e', 'i', 'o', 'u']) {
        "an"
    } else {
        "a"
    };
    let mut words = vec![article, first];
    if let Some(adjective) = app.pattern.word() {
        if app.colors[1] != app.colors[0].default_partner() {
            words.extend(["and", app.colors[1].word()]);
        }
        words.push(adjective);
    }
    words.push(app.shape.word());
    if app.on_table {
        words.extend(["on", "a", "table"]);
    }
    words.join(" ")
}

/// Parses a caption of the grammar above (case, extra spaces and a final period are ignored).
pub fn parse_caption(text: &str) -> Result<Appearance, CaptionError> {
    let fail = |msg: String| CaptionError {
        caption: text.to_string(),
        msg,
    };
    let lower = text.trim().trim_end_matches('.').to_lowercase();
    let words: Vec<&str> = lower.split_whitespace().collect();
    let mut at = 0;
    let next = |at: &mut usize| -> Option<&str> {
        let w = words.get(*at).copied();
        *at += 1;
        w
    };
    let expect_color = |w: Option<&str>| -> Result<ColorName, CaptionError> {
        let w = w.ok_or_else(|| fail("ends where a colour should follow".into()))?;
        ColorName::from_word(w).ok_or_else(|| {
            fail(format!(
                "'{w}' is not a colour (colours: {})",
                ColorName::ALL.map(|c| c.word()).join(", ")
            ))
        })
    };
    match next(&mut at) {
        Some("a" | "an") => {}
        Some(w) => return Err(fail(format!("must start with 'a' or 'an', not '{w}'"))),
        None => return Err(fail("is empty".into())),
    }
    let first = expect_color(next(&mut at))?;
    let mut second = None;
    if words.get(at) == Some(&"and") {
        at += 1;
        let c = expect_color(next(&mut at))?;
        if c == first {
            return Err(fail(format!("names {} twice", c.word())));
        }
        second = Some(c);
    }
    let mut pattern = PatternKind::Solid;
    if let Some(p) = words.get(at).and_then(|w| PatternKind::from_word(w)) {
        pattern = p;
        at += 1;
    }
    if second.is_some() && pattern == PatternKind::Solid {
        return Err(fail(
            "two colours need a pattern (striped, checkered, dotted, gradient)".into(),
        ));
    }
    let shape_word = next(&mut at).ok_or_else(|| fail("has no shape".into()))?;
    let shape = ShapeKind::from_word(shape_word).ok_or_else(|| {
        fail(format!(
            "'{shape_word}' is not a shape (shapes: {})",
            ShapeKind::ALL.map(|s| s.word()).join(", ")
        ))
    })?;
    let on_table = match &words[at.min(words.len())..] {
        [] => false,
        ["on", "a", "table"] => true,
        rest => {
            return Err(fail(format!(
                "unexpected '{}' after the shape (only 'on a table' may follow)",
                rest.join(" ")
            )))
        }
    };
    if on_table && !shape.can_stand_on_table() {
        return Err(fail(format!("a {} cannot stand on a table", shape.word())));
    }
    Ok(Appearance {
        shape,
        colors: [first, second.unwrap_or(first.default_partner())],
        pattern,
        on_table,
    }
    .normalized())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    #[test]
    fn vocabulary_is_exactly_the_words_of_the_grammar() {
        let mut words: HashSet<&str> = ["a", "an", "and", "on", "table"].into();
        words.extend(ColorName::ALL.map(|c| c.word()));
        words.extend(PatternKind::ALL.iter().filter_map(|p| p.word()));
        words.extend(ShapeKind::ALL.map(|s| s.word()));
        let vocab: HashSet<&str> = VOCABULARY.iter().copied().collect();
        assert_eq!(vocab.len(), VOCABULARY.len(), "duplicates in VOCABULARY");
        assert_eq!(vocab, words);
    }

    #[test]
    fn every_appearance_roundtrips_through_its_caption() {
        let mut seen = HashSet::new();
        for shape in ShapeKind::ALL {
            for a in ColorName::ALL {
                for b in ColorName::ALL {
                    if a == b {
                        continue;
                    }
                    for pattern in PatternKind::ALL {
                        for on_table in [false, true] {
                            if on_table && !shape.can_stand_on_table() {
                                continue;
                            }
                            let app = Appearance {
                                shape,
                                colors: [a, b],
                                pattern,
                                on_table,
                            };
                            let text = caption(&app);
                            assert!(text.split(' ').all(|w| VOCABULARY.contains(&w)), "{text}");
                            assert_eq!(parse_caption(&text).unwrap(), app.normalized(), "{text}");
                            seen.insert(text);
                        }
                    }
                }
            }
        }
        // Distinct normalised appearances give distinct captions.
        assert!(seen.len() > 5000);
    }

    #[test]
    fn examples_and_errors() {
        let app = parse_caption("A red striped vase on a table.").unwrap();
        assert_eq!(
            app,
            Appearance {
                shape: ShapeKind::Vase,
                colors: [ColorName::Red, ColorName::White],
                pattern: PatternKind::Stripes,
                on_table: true
            }
        );
        assert_eq!(caption(&app), "a red striped vase on a table");
        let app = parse_caption("an orange and  blue checkered cube").unwrap();
        assert_eq!(app.colors, [ColorName::Orange, ColorName::Blue]);
        assert_eq!(caption(&app), "an orange and blue checkered cube");
        assert_eq!(
            parse_caption("a white dotted sphere").unwrap().colors[1],
            ColorName::Black
        );
        assert_eq!(
            caption(&parse_caption("a blue sphere").unwrap()),
            "a blue sphere"
        );
        for (bad, needle) in [
            ("", "empty"),
            ("the red sphere", "start"),
            ("a teal sphere", "teal"),
            ("a red and blue sphere", "pattern"),
            ("a red and red striped cube", "twice"),
            ("a red striped", "shape"),
            ("a red blob", "blob"),
            ("a red sphere on the floor", "on the floor"),
            ("a brown table on a table", "cannot stand"),
        ] {
            let e = parse_caption(bad).unwrap_err();
            assert!(e.to_string().contains(needle), "{bad}: {e}");
        }
    }
}
