//! Scene specifications: what a scene contains, serialisable, generated from a seed or from a caption.
//!
//! A scene is one main object (the thing the caption describes), optionally standing on a table, on a
//! floor disc, in front of a plain background. Coordinates: z is up, the floor is the plane z = 0, lengths
//! are in world units with objects about one unit across.

use super::caption::{caption, parse_caption, Appearance, CaptionError};
use super::palette::{ColorName, ColorSpec};
use super::pattern::{Orientation, Pattern, PatternKind};
use super::WorldError;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f32::consts::TAU;

/// The kinds of objects of the caption vocabulary.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShapeKind {
    Sphere,
    Cube,
    Cylinder,
    Cone,
    Torus,
    Vase,
    Table,
    Snowman,
    Mushroom,
}

impl ShapeKind {
    pub const ALL: [ShapeKind; 9] = [
        ShapeKind::Sphere,
        ShapeKind::Cube,
        ShapeKind::Cylinder,
        ShapeKind::Cone,
        ShapeKind::Torus,
        ShapeKind::Vase,
        ShapeKind::Table,
        ShapeKind::Snowman,
        ShapeKind::Mushroom,
    ];

    pub fn word(self) -> &'static str {
        match self {
            ShapeKind::Sphere => "sphere",
            ShapeKind::Cube => "cube",
            ShapeKind::Cylinder => "cylinder",
            ShapeKind::Cone => "cone",
            ShapeKind::Torus => "torus",
            ShapeKind::Vase => "vase",
            ShapeKind::Table => "table",
            ShapeKind::Snowman => "snowman",
            ShapeKind::Mushroom => "mushroom",
        }
    }

    pub fn from_word(word: &str) -> Option<ShapeKind> {
        ShapeKind::ALL.into_iter().find(|s| s.word() == word)
    }

    /// Everything but a table may stand on a table.
    pub fn can_stand_on_table(self) -> bool {
        self != ShapeKind::Table
    }
}

/// A shape with its dimensions (object-local: standing on z = 0, centred on the z axis, facing +x).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Shape {
    Sphere {
        radius: f32,
    },
    Cube {
        size: f32,
    },
    Cylinder {
        radius: f32,
        height: f32,
    },
    Cone {
        radius: f32,
        height: f32,
    },
    /// Lying flat on the floor.
    Torus {
        major: f32,
        minor: f32,
    },
    /// `radius` at its widest.
    Vase {
        radius: f32,
        height: f32,
    },
    Table {
        width: f32,
        depth: f32,
        height: f32,
    },
    /// `radius` of the bottom ball.
    Snowman {
        radius: f32,
    },
    Mushroom {
        cap_radius: f32,
        stem_height: f32,
    },
}

/// Proportions of composite shapes, shared by the builder and the bounds computed here.
pub(crate) mod proportions {
    /// Snowman ball radii relative to the bottom one, and how much neighbouring balls overlap.
    pub const SNOWMAN_RADII: [f32; 3] = [1.0, 0.72, 0.5];
    pub const SNOWMAN_OVERLAP: f32 = 0.8;
    /// Mushroom cap height over its radius, stem radius over cap radius.
    pub const MUSHROOM_CAP_HEIGHT: f32 = 0.75;
    pub const MUSHROOM_STEM_RADIUS: f32 = 0.3;
    /// Table top thickness and leg radius, world units.
    pub const TABLE_TOP: f32 = 0.06;
    pub const TABLE_LEG: f32 = 0.035;

    /// Heights of the snowman's ball centres for a bottom radius.
    pub fn snowman_centres(radius: f32) -> [f32; 3] {
        let r = SNOWMAN_RADII.map(|f| f * radius);
        let c0 = r[0];
        let c1 = c0 + SNOWMAN_OVERLAP * (r[0] + r[1]);
        let c2 = c1 + SNOWMAN_OVERLAP * (r[1] + r[2]);
        [c0, c1, c2]
    }
}

impl Shape {
    pub fn kind(&self) -> ShapeKind {
        match self {
            Shape::Sphere { .. } => ShapeKind::Sphere,
            Shape::Cube { .. } => ShapeKind::Cube,
            Shape::Cylinder { .. } => ShapeKind::Cylinder,
            Shape::Cone { .. } => ShapeKind::Cone,
            Shape::Torus { .. } => ShapeKind::Torus,
            Shape::Vase { .. } => ShapeKind::Vase,
            Shape::Table { .. } => ShapeKind::Table,
            Shape::Snowman { .. } => ShapeKind::Snowman,
            Shape::Mushroom { .. } => ShapeKind::Mushroom,
        }
    }

    /// Random dimensions for a kind, about one unit across.
    pub fn random<R: Rng>(kind: ShapeKind, rng: &mut R) -> Shape {
        let mut u = |lo: f32, hi: f32| rng.gen_range(lo..=hi);
        match kind {
            ShapeKind::Sphere => Shape::Sphere {
                radius: u(0.38, 0.5),
            },
            ShapeKind::Cube => Shape::Cube { size: u(0.6, 0.8) },
            ShapeKind::Cylinder => Shape::Cylinder {
                radius: u(0.26, 0.4),
                height: u(0.6, 1.0),
            },
            ShapeKind::Cone => Shape::Cone {
                radius: u(0.3, 0.45),
                height: u(0.7, 1.0),
            },
            ShapeKind::Torus => Shape::Torus {
                major: u(0.34, 0.44),
                minor: u(0.12, 0.17),
            },
            ShapeKind::Vase => Shape::Vase {
                radius: u(0.26, 0.36),
                height: u(0.7, 1.0),
            },
            ShapeKind::Table => {
                let width = u(0.95, 1.25);
                Shape::Table {
                    width,
                    depth: width * u(0.65, 0.85),
                    height: u(0.5, 0.7),
                }
            }
            ShapeKind::Snowman => Shape::Snowman {
                radius: u(0.24, 0.3),
            },
            ShapeKind::Mushroom => Shape::Mushroom {
                cap_radius: u(0.36, 0.46),
                stem_height: u(0.3, 0.45),
            },
        }
    }

    /// The same shape scaled by `f`.
    pub fn scaled(self, f: f32) -> Shape {
        match self {
            Shape::Sphere { radius } => Shape::Sphere { radius: radius * f },
            Shape::Cube { size } => Shape::Cube { size: size * f },
            Shape::Cylinder { radius, height } => Shape::Cylinder {
                radius: radius * f,
                height: height * f,
            },
            Shape::Cone { radius, height } => Shape::Cone {
                radius: radius * f,
                height: height * f,
            },
            Shape::Torus { major, minor } => Shape::Torus {
                major: major * f,
                minor: minor * f,
            },
            Shape::Vase { radius, height } => Shape::Vase {
                radius: radius * f,
                height: height * f,
            },
            Shape::Table {
                width,
                depth,
                height,
            } => Shape::Table {
                width: width * f,
                depth: depth * f,
                height: height * f,
            },
            Shape::Snowman { radius } => Shape::Snowman { radius: radius * f },
            Shape::Mushroom {
                cap_radius,
                stem_height,
            } => Shape::Mushroom {
                cap_radius: cap_radius * f,
                stem_height: stem_height * f,
            },
        }
    }

    /// Height of the top above the base.
    pub fn height(&self) -> f32 {
        use proportions::*;
        match *self {
            Shape::Sphere { radius } => 2.0 * radius,
            Shape::Cube { size } => size,
            Shape::Cylinder { height, .. } | Shape::Cone { height, .. } => height,
            Shape::Torus { minor, .. } => 2.0 * minor,
            // The lip adds a little on top (see the builder).
            Shape::Vase { radius, height } => height + VASE_LIP * radius,
            Shape::Table { height, .. } => height,
            Shape::Snowman { radius } => snowman_centres(radius)[2] + SNOWMAN_RADII[2] * radius,
            Shape::Mushroom {
                cap_radius,
                stem_height,
            } => stem_height + MUSHROOM_CAP_HEIGHT * cap_radius,
        }
    }

    /// Half-extents of the footprint along local x and y (a bounding rectangle of the shape seen from
    /// above, centred on the axis).
    pub fn half_footprint(&self) -> [f32; 2] {
        match *self {
            Shape::Sphere { radius }
            | Shape::Cylinder { radius, .. }
            | Shape::Cone { radius, .. } => [radius; 2],
            Shape::Cube { size } => [0.5 * size; 2],
            Shape::Torus { major, minor } => [major + minor; 2],
            Shape::Vase { radius, .. } => [radius; 2],
            Shape::Table { width, depth, .. } => [0.5 * width, 0.5 * depth],
            // The nose sticks out of the head but stays within the bottom ball's radius.
            Shape::Snowman { radius } => [radius; 2],
            Shape::Mushroom { cap_radius, .. } => [cap_radius; 2],
        }
    }

    /// Circumference at the widest, the reference for pattern cells around the object.
    pub fn circumference(&self) -> f32 {
        match *self {
            Shape::Cube { size } => 4.0 * size,
            Shape::Table { width, depth, .. } => 2.0 * (width + depth),
            _ => TAU * self.half_footprint()[0],
        }
    }

    /// A representative size (the larger of height and width), for pattern scales.
    pub fn extent(&self) -> f32 {
        let [hx, hy] = self.half_footprint();
        self.height().max(2.0 * hx.max(hy))
    }
}

/// The vase's lip radius relative to the vase radius.
pub(crate) const VASE_LIP: f32 = 0.08;

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
