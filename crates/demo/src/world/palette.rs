//! The named colours of the world, their jitter, and a perceptual colour distance (CIELAB) for the oracle.

use rand::Rng;
use serde::{Deserialize, Serialize};

/// A colour name of the caption vocabulary.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ColorName {
    Red,
    Green,
    Blue,
    Yellow,
    White,
    Black,
    Orange,
    Purple,
    Pink,
    Gray,
    Brown,
}

impl ColorName {
    pub const ALL: [ColorName; 11] = [
        ColorName::Red,
        ColorName::Green,
        ColorName::Blue,
        ColorName::Yellow,
        ColorName::White,
        ColorName::Black,
        ColorName::Orange,
        ColorName::Purple,
        ColorName::Pink,
        ColorName::Gray,
        ColorName::Brown,
    ];

    /// The caption word.
    pub fn word(self) -> &'static str {
        match self {
            ColorName::Red => "red",
            ColorName::Green => "green",
            ColorName::Blue => "blue",
            ColorName::Yellow => "yellow",
            ColorName::White => "white",
            ColorName::Black => "black",
            ColorName::Orange => "orange",
            ColorName::Purple => "purple",
            ColorName::Pink => "pink",
            ColorName::Gray => "gray",
            ColorName::Brown => "brown",
        }
    }

    pub fn from_word(word: &str) -> Option<ColorName> {
        // "grey" is accepted as a spelling of "gray" when parsing; captions always write "gray".
        if word == "grey" {
            return Some(ColorName::Gray);
        }
        ColorName::ALL.into_iter().find(|c| c.word() == word)
    }

    /// The reference sRGB value in [0, 1].
    pub fn rgb(self) -> [f32; 3] {
        match self {
            ColorName::Red => [0.86, 0.11, 0.10],
            ColorName::Green => [0.13, 0.62, 0.20],
            ColorName::Blue => [0.12, 0.28, 0.86],
            ColorName::Yellow => [0.96, 0.86, 0.12],
            ColorName::White => [0.96, 0.96, 0.95],
            ColorName::Black => [0.07, 0.07, 0.08],
            ColorName::Orange => [0.98, 0.52, 0.08],
            ColorName::Purple => [0.52, 0.18, 0.70],
            ColorName::Pink => [0.98, 0.56, 0.76],
            ColorName::Gray => [0.50, 0.50, 0.50],
            ColorName::Brown => [0.48, 0.28, 0.13],
        }
    }

    /// The second colour a caption leaves unsaid: "a red striped vase" is red and white; white things get
    /// black as their second colour.
    pub fn default_partner(self) -> ColorName {
        if self == ColorName::White {
            ColorName::Black
        } else {
            ColorName::White
        }
    }

    /// Whether two named colours are far enough apart to form a readable pattern.
    pub fn contrasts_with(self, other: ColorName) -> bool {
        lab_distance(self.rgb(), other.rgb()) >= MIN_PATTERN_CONTRAST
    }
}

/// Smallest CIELAB distance between the two colours of a pattern (red/orange or blue/purple fall below).
pub const MIN_PATTERN_CONTRAST: f32 = 40.0;

/// A named colour with the exact sRGB value of one instance.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ColorSpec {
    pub name: ColorName,
    pub rgb: [f32; 3],
}

impl ColorSpec {
    /// The reference value of a name, without jitter.
    pub fn exact(name: ColorName) -> Self {
        Self {
            name,
            rgb: name.rgb(),
        }
    }

    /// The reference value moved by up to `jitter` per channel, clamped to [0, 1].
    pub fn jittered<R: Rng>(name: ColorName, jitter: f32, rng: &mut R) -> Self {
        let base = name.rgb();
        let rgb = if jitter > 0.0 {
            base.map(|c| (c + rng.gen_range(-jitter..=jitter)).clamp(0.0, 1.0))
        } else {
            base
        };
        Self { name, rgb }
    }
}

/// sRGB in [0, 1] to CIELAB (D65).
pub fn srgb_to_lab(rgb: [f32; 3]) -> [f32; 3] {
    let lin = rgb.map(|c| {
        let c = c.clamp(0.0, 1.0);
        if c <= 0.040_45 {
            c / 12.92
        } else {
            ((c + 0.055) / 1.055).powf(2.4)
        }
    });
    let x = (0.412_456_4 * lin[0] + 0.357_576_1 * lin[1] + 0.180_437_5 * lin[2]) / 0.950_47;
    let y = 0.212_672_9 * lin[0] + 0.715_152_2 * lin[1] + 0.072_175 * lin[2];
    let z = (0.019_333_9 * lin[0] + 0.119_192 * lin[1] + 0.950_304_1 * lin[2]) / 1.088_83;
    let f = |t: f32| {
        if t > 0.008_856 {
            t.cbrt()
        } else {
            7.787 * t + 16.0 / 116.0
        }
    };
    let (fx, fy, fz) = (f(x), f(y), f(z));
    [116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)]
}

/// Euclidean distance in CIELAB of two sRGB colours.
pub fn lab_distance(a: [f32; 3], b: [f32; 3]) -> f32 {
    let (la, lb) = (srgb_to_lab(a), srgb_to_lab(b));
    ((la[0] - lb[0]).powi(2) + (la[1] - lb[1]).powi(2) + (la[2] - lb[2]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn words_roundtrip_and_lab_reference_points() {
        for c in ColorName::ALL {
            assert_eq!(ColorName::from_word(c.word()), Some(c));
        }
        assert_eq!(ColorName::from_word("grey"), Some(ColorName::Gray));
        assert_eq!(ColorName::from_word("teal"), None);
        let white = srgb_to_lab([1.0; 3]);
        assert!((white[0] - 100.0).abs() < 0.1 && white[1].abs() < 0.1 && white[2].abs() < 0.1);
        let black = srgb_to_lab([0.0; 3]);
        assert!(black[0].abs() < 1e-3);
        // Pure red is L≈53, a≈80, b≈67.
        let red = srgb_to_lab([1.0, 0.0, 0.0]);
        assert!(
            (red[0] - 53.2).abs() < 0.5
                && (red[1] - 80.1).abs() < 1.0
                && (red[2] - 67.2).abs() < 1.0
        );
    }

    #[test]
    fn every_colour_contrasts_with_its_default_partner_and_jitter_stays_close() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for c in ColorName::ALL {
            assert!(c.contrasts_with(c.default_partner()), "{c:?}");
            assert!(!c.contrasts_with(c));
            let j = ColorSpec::jittered(c, 0.04, &mut rng);
            assert!(lab_distance(j.rgb, c.rgb()) < 12.0);
            assert!(j.rgb.iter().all(|v| (0.0..=1.0).contains(v)));
        }
        // Colours with different names are told apart: nearest reference of each is itself.
        for c in ColorName::ALL {
            let nearest = ColorName::ALL
                .into_iter()
                .min_by(|a, b| {
                    lab_distance(a.rgb(), c.rgb()).total_cmp(&lab_distance(b.rgb(), c.rgb()))
                })
                .unwrap();
            assert_eq!(nearest, c);
        }
    }
}
