//! Scene specifications: what a scene contains, serialisable, generated from a seed or from a caption.
//!
//! A scene is one main object (the thing the caption describes), optionally standing on a table, on a
//! floor disc, in front of a plain background. Coordinates: z is up, the floor is the plane z = 0, lengths
//! are in world units with objects about one unit across.

use super::caption::{caption, parse_caption, Appearance, CaptionError};
use super::palette::{ColorName, ColorSpec};
use super::pattern::{Orientation, Pattern, PatternKind};
use super::shape::{Shape, ShapeKind};
use super::WorldError;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f32::consts::TAU;

/// One object placed in the world.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectSpec {
    pub shape: Shape,
    /// World position of the base centre (the point of the axis at the bottom).
    pub position: [f32; 3],
    /// Rotation about the vertical axis, radians (0: the object's front faces +x).
    pub yaw: f32,
    /// First and second colour of the pattern.
    pub colors: [ColorSpec; 2],
    pub pattern: Pattern,
    /// Seed of the surface sampling (where exactly the Gaussians go).
    pub seed: u64,
}

impl ObjectSpec {
    /// World-space bounds (min, max) of the object, from its shape and placement.
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let [hx, hy] = self.shape.half_footprint();
        let (ex, ey) = match self.shape.kind() {
            // Rectangular footprints turn with the yaw: project the half-extents on the world axes.
            ShapeKind::Cube | ShapeKind::Table => {
                let (s, c) = self.yaw.sin_cos();
                (hx * c.abs() + hy * s.abs(), hx * s.abs() + hy * c.abs())
            }
            // Round footprints do not.
            _ => (hx, hy),
        };
        let p = self.position;
        (
            [p[0] - ex, p[1] - ey, p[2]],
            [p[0] + ex, p[1] + ey, p[2] + self.shape.height()],
        )
    }
}

/// The floor: a disc at z = 0 with a faint two-tone tiling.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FloorSpec {
    pub radius: f32,
    pub colors: [[f32; 3]; 2],
    /// Tile size, world units.
    pub tile: f32,
    pub seed: u64,
}

/// A whole scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneSpec {
    /// The object the caption describes.
    pub main: ObjectSpec,
    /// The table the main object stands on, if any.
    pub support: Option<ObjectSpec>,
    pub floor: FloorSpec,
    /// Render background colour (what is seen past the floor).
    pub background: [f32; 3],
}

/// Choices the generator draws from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeneratorSettings {
    pub shapes: Vec<ShapeKind>,
    pub colors: Vec<ColorName>,
    /// Pattern families, drawn uniformly (list a family twice to make it twice as likely).
    pub patterns: Vec<PatternKind>,
    /// Chance that an object that can stand on a table does.
    pub table_probability: f32,
    /// Chance that a two-colour pattern uses the first colour's default partner as its second colour.
    pub default_partner_probability: f32,
    /// Per-channel jitter of the named colours.
    pub color_jitter: f32,
    /// Period of stripes, checks and dots relative to the object's extent.
    pub period_range: [f32; 2],
    /// Gradient transition length relative to the object's extent along its surface.
    pub gradient_range: [f32; 2],
    pub background: [f32; 3],
}

impl Default for GeneratorSettings {
    fn default() -> Self {
        Self {
            shapes: ShapeKind::ALL.to_vec(),
            colors: ColorName::ALL.to_vec(),
            patterns: PatternKind::ALL.to_vec(),
            table_probability: 0.25,
            default_partner_probability: 0.5,
            color_jitter: 0.04,
            period_range: [0.22, 0.38],
            gradient_range: [0.45, 0.9],
            background: [0.86, 0.89, 0.94],
        }
    }
}

/// Floor colour pairs: light neutral tones, far from the object palette's saturated colours.
const FLOOR_TONES: [[[f32; 3]; 2]; 3] = [
    [[0.74, 0.70, 0.64], [0.68, 0.64, 0.58]],
    [[0.64, 0.66, 0.68], [0.58, 0.60, 0.62]],
    [[0.71, 0.63, 0.53], [0.65, 0.57, 0.47]],
];

/// Scale of an object standing on a table, so the pair stays about as large as a lone object.
const ON_TABLE_SCALE: f32 = 0.7;

impl SceneSpec {
    /// A random scene.
    pub fn random(seed: u64, settings: &GeneratorSettings) -> SceneSpec {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let app = random_appearance(&mut rng, settings);
        Self::with_rng(&app, &mut rng, settings)
    }

    /// A random scene that looks as `app` says.
    pub fn from_appearance(app: &Appearance, seed: u64, settings: &GeneratorSettings) -> SceneSpec {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        Self::with_rng(app, &mut rng, settings)
    }

    /// A random scene matching a caption.
    pub fn from_caption(
        text: &str,
        seed: u64,
        settings: &GeneratorSettings,
    ) -> Result<SceneSpec, CaptionError> {
        Ok(Self::from_appearance(&parse_caption(text)?, seed, settings))
    }

    fn with_rng(app: &Appearance, rng: &mut ChaCha8Rng, settings: &GeneratorSettings) -> SceneSpec {
        let app = app.normalized();
        let on_table = app.on_table && app.shape.can_stand_on_table();
        let mut shape = Shape::random(app.shape, rng);
        if on_table {
            shape = shape.scaled(ON_TABLE_SCALE);
        }
        let colors = app
            .colors
            .map(|c| ColorSpec::jittered(c, settings.color_jitter, rng));
        let pattern = random_pattern(app.pattern, &shape, rng, settings);
        let yaw = rng.gen_range(0.0..TAU);
        let seed = rng.gen();
        let support = on_table.then(|| {
            let [hx, hy] = shape.half_footprint();
            let r = hx.max(hy);
            let width = (2.6 * r).max(0.9) * rng.gen_range(1.0..1.2);
            let depth = (2.3 * r).max(0.65).min(width);
            let table = Shape::Table {
                width,
                depth,
                height: rng.gen_range(0.5..0.62),
            };
            ObjectSpec {
                shape: table,
                position: [0.0; 3],
                yaw: rng.gen_range(0.0..TAU),
                colors: [
                    ColorSpec::jittered(ColorName::Brown, settings.color_jitter, rng),
                    ColorSpec::exact(ColorName::White),
                ],
                pattern: Pattern::solid(),
                seed: rng.gen(),
            }
        });
        let base = support.as_ref().map_or(0.0, |t| t.shape.height());
        let floor_tones = FLOOR_TONES[rng.gen_range(0..FLOOR_TONES.len())];
        let floor = FloorSpec {
            radius: 8.0,
            colors: floor_tones,
            tile: rng.gen_range(0.35..0.5),
            seed: rng.gen(),
        };
        SceneSpec {
            main: ObjectSpec {
                shape,
                position: [0.0, 0.0, base],
                yaw,
                colors,
                pattern,
                seed,
            },
            support,
            floor,
            background: settings.background,
        }
    }

    /// What the caption of this scene says.
    pub fn appearance(&self) -> Appearance {
        Appearance {
            shape: self.main.shape.kind(),
            colors: self.main.colors.map(|c| c.name),
            pattern: self.main.pattern.kind,
            on_table: self.support.is_some(),
        }
        .normalized()
    }

    /// The caption of this scene.
    pub fn caption(&self) -> String {
        caption(&self.appearance())
    }

    /// The same scene (same geometry, same Gaussians) with the main object's colours and pattern family
    /// changed to what `app` says. Pattern parameters (period, phase, orientation) are kept, so a colour
    /// change keeps the layout; colours whose name does not change keep their exact value, new ones take
    /// the reference value. Fails when `app` names another shape or another support.
    pub fn with_appearance(&self, app: &Appearance) -> Result<SceneSpec, WorldError> {
        let app = app.normalized();
        let current = self.appearance();
        if app.shape != current.shape || app.on_table != current.on_table {
            return Err(WorldError::Incompatible(format!(
                "cannot turn \"{}\" into \"{}\": only colours and patterns can change",
                self.caption(),
                caption(&app)
            )));
        }
        let mut out = self.clone();
        for (slot, name) in out.main.colors.iter_mut().zip(app.colors) {
            if slot.name != name {
                *slot = ColorSpec::exact(name);
            }
        }
        let was_gradient = self.main.pattern.kind == PatternKind::Gradient;
        let is_gradient = app.pattern == PatternKind::Gradient;
        let pattern = &mut out.main.pattern;
        pattern.kind = app.pattern;
        if was_gradient != is_gradient {
            // The period means something else for gradients; take the middle of the default range.
            let d = GeneratorSettings::default();
            pattern.period = if is_gradient {
                0.5 * (d.gradient_range[0] + d.gradient_range[1])
            } else {
                0.5 * (d.period_range[0] + d.period_range[1]) * self.main.shape.extent()
            };
        }
        Ok(out)
    }

    /// [`SceneSpec::with_appearance`] from a caption.
    pub fn with_caption(&self, text: &str) -> Result<SceneSpec, WorldError> {
        self.with_appearance(&parse_caption(text)?)
    }

    /// Whether `other` has the same geometry (shapes, placement, sampling seeds), so both build into the
    /// same Gaussians and differ only in colour.
    pub fn same_geometry(&self, other: &SceneSpec) -> bool {
        let geo = |o: &ObjectSpec| (o.shape, o.position, o.yaw, o.seed);
        geo(&self.main) == geo(&other.main)
            && self.support.as_ref().map(geo) == other.support.as_ref().map(geo)
            && self.floor == other.floor
    }

    /// World bounds of the objects (floor excluded).
    pub fn object_bounds(&self) -> ([f32; 3], [f32; 3]) {
        let (mut lo, mut hi) = self.main.bounds();
        if let Some(t) = &self.support {
            let (l, h) = t.bounds();
            for a in 0..3 {
                lo[a] = lo[a].min(l[a]);
                hi[a] = hi[a].max(h[a]);
            }
        }
        (lo, hi)
    }
}

fn random_appearance<R: Rng>(rng: &mut R, settings: &GeneratorSettings) -> Appearance {
    let shapes = if settings.shapes.is_empty() {
        &ShapeKind::ALL[..]
    } else {
        &settings.shapes[..]
    };
    let colors = if settings.colors.is_empty() {
        &ColorName::ALL[..]
    } else {
        &settings.colors[..]
    };
    let shape = *shapes.choose(rng).unwrap_or(&ShapeKind::Sphere);
    let pattern = *settings.patterns.choose(rng).unwrap_or(&PatternKind::Solid);
    let first = *colors.choose(rng).unwrap_or(&ColorName::Red);
    let partners: Vec<ColorName> = colors
        .iter()
        .copied()
        .filter(|&c| c != first.default_partner() && first.contrasts_with(c))
        .collect();
    let second = if rng.gen::<f32>() < settings.default_partner_probability || partners.is_empty() {
        first.default_partner()
    } else {
        *partners.choose(rng).unwrap_or(&first.default_partner())
    };
    let on_table = shape.can_stand_on_table() && rng.gen::<f32>() < settings.table_probability;
    Appearance {
        shape,
        colors: [first, second],
        pattern,
        on_table,
    }
    .normalized()
}

fn random_pattern<R: Rng>(
    kind: PatternKind,
    shape: &Shape,
    rng: &mut R,
    settings: &GeneratorSettings,
) -> Pattern {
    let range = if kind == PatternKind::Gradient {
        settings.gradient_range
    } else {
        settings.period_range.map(|f| f * shape.extent())
    };
    let period = if range[1] > range[0] {
        rng.gen_range(range[0]..range[1])
    } else {
        range[0]
    };
    Pattern {
        kind,
        orientation: *Orientation::ALL
            .choose(rng)
            .unwrap_or(&Orientation::Horizontal),
        period,
        phase: [rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0)],
        handedness: if rng.gen::<bool>() { 1 } else { -1 },
        dot_radius: rng.gen_range(0.25..0.34),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_scenes_are_deterministic_and_varied() {
        let s = GeneratorSettings::default();
        assert_eq!(SceneSpec::random(7, &s), SceneSpec::random(7, &s));
        assert_ne!(SceneSpec::random(7, &s), SceneSpec::random(8, &s));
        let mut kinds = std::collections::HashSet::new();
        let mut patterns = std::collections::HashSet::new();
        let mut tables = 0;
        for seed in 0..300 {
            let spec = SceneSpec::random(seed, &s);
            kinds.insert(spec.main.shape.kind());
            patterns.insert(spec.main.pattern.kind);
            tables += spec.support.is_some() as usize;
            let app = spec.appearance();
            if app.pattern.uses_second_color() {
                assert!(
                    app.colors[0].contrasts_with(app.colors[1]),
                    "{}",
                    spec.caption()
                );
            }
            // The main object stands on its support, and fits on it.
            if let Some(t) = &spec.support {
                assert_eq!(spec.main.position[2], t.shape.height());
                let [hx, hy] = spec.main.shape.half_footprint();
                let [tx, ty] = t.shape.half_footprint();
                assert!(hx.max(hy) < tx.min(ty), "{}", spec.caption());
            } else {
                assert_eq!(spec.main.position[2], 0.0);
            }
            let json = serde_json::to_string(&spec).unwrap();
            assert_eq!(serde_json::from_str::<SceneSpec>(&json).unwrap(), spec);
        }
        assert_eq!(kinds.len(), ShapeKind::ALL.len());
        assert_eq!(patterns.len(), PatternKind::ALL.len());
        assert!(tables > 20 && tables < 120, "{tables}");
    }

    #[test]
    fn captions_drive_scenes_and_edits_keep_geometry() {
        let s = GeneratorSettings::default();
        let spec = SceneSpec::from_caption("a red striped vase on a table", 3, &s).unwrap();
        assert_eq!(spec.caption(), "a red striped vase on a table");
        assert!(spec.support.is_some());
        let target = spec.with_caption("a green dotted vase on a table").unwrap();
        assert!(spec.same_geometry(&target));
        assert_eq!(target.caption(), "a green dotted vase on a table");
        assert_eq!(target.main.pattern.phase, spec.main.pattern.phase);
        assert_eq!(
            target.main.colors[1], spec.main.colors[1],
            "white stays the same white"
        );
        assert_eq!(target.main.colors[0], ColorSpec::exact(ColorName::Green));
        assert!(spec
            .with_caption("a green dotted sphere on a table")
            .is_err());
        assert!(spec.with_caption("a green dotted vase").is_err());
        let g = spec.with_caption("a red gradient vase on a table").unwrap();
        assert!(g.main.pattern.period < 1.0);
        assert!(!spec.same_geometry(
            &SceneSpec::from_caption("a red striped vase on a table", 4, &s).unwrap()
        ));
    }
}
