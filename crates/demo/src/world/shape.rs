//! The shapes a scene's objects take: the kinds the caption grammar names ([`ShapeKind`]) and their
//! dimensions ([`Shape`]), with the proportions of composite shapes that the builder and the bounds share.

use rand::Rng;
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
