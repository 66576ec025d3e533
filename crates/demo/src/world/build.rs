//! Turning a [`SceneSpec`] into Gaussians, directly (no fitting): every surface element becomes one flat,
//! opaque Gaussian lying in the surface's tangent plane, wide enough to overlap its neighbours and thin
//! along the normal, coloured by the object's pattern at that point (SH degree 0).

use super::geometry::{
    box_faces, frame_quaternion, revolve, unit_or_z, Element, Motion, Part, Profile, VMeasure,
};
use super::pattern::{PatternFrame, SurfacePoint};
use super::shape::{proportions::*, Shape, VASE_LIP};
use super::spec::{ObjectSpec, SceneSpec};
use super::WorldError;
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use splat::GaussianScene;
use std::f32::consts::{FRAC_PI_2, PI};

/// SH band-0 constant: colour = 0.5 + C0 * dc.
pub const SH_C0: f32 = 0.282_094_8;

/// Object ids in [`GaussianLabels::object`].
pub const MAIN: u8 = 0;
pub const SUPPORT: u8 = 1;
pub const FLOOR: u8 = 2;
/// Number of object ids (main, support, floor).
pub const OBJECT_IDS: usize = 3;

/// Which colour of its object a Gaussian shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[repr(u8)]
pub enum Slot {
    /// The first colour of the pattern.
    First = 0,
    /// The second colour of the pattern.
    Second = 1,
    /// A colour that does not come from the pattern (the floor, a mushroom's stem, a snowman's nose).
    Fixed = 2,
}

/// How densely and how the surfaces are covered.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BuildSettings {
    /// Distance between neighbouring Gaussians on objects, world units (objects are about one unit
    /// across: 0.016 gives 5-20k Gaussians per object).
    pub spacing: f32,
    /// The same on the floor, which is large and plain.
    pub floor_spacing: f32,
    /// Standard deviation along the surface relative to the spacing (> 0.5 so neighbours overlap).
    pub overlap: f32,
    /// Standard deviation along the normal relative to the one along the surface.
    pub thickness: f32,
    pub opacity: f32,
}

impl Default for BuildSettings {
    fn default() -> Self {
        Self {
            spacing: 0.016,
            floor_spacing: 0.06,
            overlap: 0.75,
            thickness: 0.1,
            opacity: 0.97,
        }
    }
}

impl BuildSettings {
    /// Settings with `spacing` on objects and the default ratios elsewhere.
    pub fn with_spacing(spacing: f32) -> Self {
        let d = Self::default();
        Self {
            spacing,
            floor_spacing: spacing * d.floor_spacing / d.spacing,
            ..d
        }
    }
}

/// Per-Gaussian labels, for oracles and masks.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianLabels {
    /// [`MAIN`], [`SUPPORT`] or [`FLOOR`].
    pub object: Vec<u8>,
    pub part: Vec<Part>,
    pub slot: Vec<Slot>,
    /// Weight of the second colour (0 or 1 except in gradients; 0 for fixed colours).
    pub mix: Vec<f32>,
}

/// A built scene: the Gaussians, their labels, and what is needed to recolour them for another spec.
#[derive(Clone, Debug)]
pub struct BuiltScene {
    pub scene: GaussianScene,
    pub labels: GaussianLabels,
    /// The spec whose colours the Gaussians currently show.
    pub spec: SceneSpec,
    surface: Vec<SurfacePoint>,
    /// Pattern frame per object id (the floor's is unused).
    frames: [PatternFrame; OBJECT_IDS],
}

/// Builds the Gaussians of a scene. Deterministic: the same spec and settings give the same scene.
pub fn build_scene(spec: &SceneSpec, settings: &BuildSettings) -> BuiltScene {
    let spacing = settings.spacing.max(1e-3);
    let floor_spacing = settings.floor_spacing.max(spacing);
    let mut scene = GaussianScene::new(0);
    let mut labels = GaussianLabels::default();
    let mut surface = Vec::new();
    let mut frames = [PatternFrame {
        circumference: 1.0,
        v_range: [0.0, 1.0],
    }; OBJECT_IDS];

    let mut objects: Vec<(u8, &ObjectSpec)> = vec![(MAIN, &spec.main)];
    if let Some(t) = &spec.support {
        objects.push((SUPPORT, t));
    }
    let mut elements = Vec::new();
    for (id, obj) in objects {
        elements.clear();
        let mut rng = ChaCha8Rng::seed_from_u64(obj.seed);
        object_elements(&obj.shape, spacing, &mut rng, &mut elements);
        frames[id as usize] = pattern_frame(&obj.shape, &elements);
        let motion = Motion::yaw(obj.yaw, obj.position);
        for e in elements.iter_mut() {
            motion.apply(e);
        }
        push_elements(
            &mut scene,
            &mut labels,
            &mut surface,
            &elements,
            id,
            spacing,
            settings,
        );
    }
    elements.clear();
    // The floor is coarse far out but as fine as the objects around their base: a coarse Gaussian's tail
    // in front of an object would be drawn over the object's foot and blur the contact.
    let (lo, hi) = spec.object_bounds();
    let reach = [lo[0], lo[1], hi[0], hi[1]]
        .iter()
        .fold(0.0_f32, |m, v| m.max(v.abs()));
    // Far out, where the floor is seen from afar, even coarser (so the disc's edge sits near the horizon).
    let fine = (reach + 0.15).min(spec.floor.radius);
    let medium = (reach + 0.6).clamp(fine, spec.floor.radius);
    let far = (reach + 2.5).clamp(medium, spec.floor.radius);
    let coarse = floor_spacing / spacing;
    let floor = Profile::start([spec.floor.radius, 0.0])
        .line_spaced([far, 0.0], Part::Floor, 4.0 * coarse)
        .line_spaced([medium, 0.0], Part::Floor, coarse)
        .line_spaced([fine, 0.0], Part::Floor, 2.0_f32.min(coarse))
        .line([0.0, 0.0], Part::Floor);
    let mut rng = ChaCha8Rng::seed_from_u64(spec.floor.seed);
    revolve(
        &floor,
        spacing,
        VMeasure::ArcLength,
        &mut rng,
        &mut elements,
    );
    push_elements(
        &mut scene,
        &mut labels,
        &mut surface,
        &elements,
        FLOOR,
        spacing,
        settings,
    );

    let mut built = BuiltScene {
        scene,
        labels,
        spec: spec.clone(),
        surface,
        frames,
    };
    built.paint();
    built
}

impl BuiltScene {
    pub fn len(&self) -> usize {
        self.scene.len()
    }

    pub fn is_empty(&self) -> bool {
        self.scene.is_empty()
    }

    /// Repaints the Gaussians with the colours of `spec`, which must have the same geometry as the spec
    /// the scene was built from ([`SceneSpec::same_geometry`]).
    pub fn recolor(&mut self, spec: &SceneSpec) -> Result<(), WorldError> {
        if !self.spec.same_geometry(spec) {
            return Err(WorldError::Incompatible(format!(
                "cannot repaint \"{}\" as \"{}\": the geometry differs",
                self.spec.caption(),
                spec.caption()
            )));
        }
        self.spec = spec.clone();
        self.paint();
        Ok(())
    }

    /// The colours `spec` gives each Gaussian (N*3), without changing the scene. `spec` must have the same
    /// geometry as the built one.
    pub fn colors_for(&self, spec: &SceneSpec) -> Result<Vec<f32>, WorldError> {
        if !self.spec.same_geometry(spec) {
            return Err(WorldError::Incompatible(format!(
                "\"{}\" and \"{}\" have different geometry",
                self.spec.caption(),
                spec.caption()
            )));
        }
        let mut out = Vec::with_capacity(3 * self.len());
        for i in 0..self.len() {
            out.extend_from_slice(&self.evaluate(spec, i).0);
        }
        Ok(out)
    }

    /// The colour each Gaussian shows (N*3), from its SH DC coefficient.
    pub fn colors(&self) -> Vec<f32> {
        self.scene.sh.iter().map(|&dc| 0.5 + SH_C0 * dc).collect()
    }

    /// One-hot label channels per Gaussian (N*6, Gaussian-major): object (main, support, floor) then slot
    /// (first, second, fixed). Rendered as extra channels they give per-pixel label weights.
    pub fn label_channels(&self) -> Vec<f32> {
        let mut out = vec![0.0; LABEL_CHANNELS * self.len()];
        for (i, chunk) in out.chunks_exact_mut(LABEL_CHANNELS).enumerate() {
            chunk[self.labels.object[i] as usize] = 1.0;
            chunk[OBJECT_IDS + self.labels.slot[i] as usize] = 1.0;
        }
        out
    }

    /// Colour, slot and mix of Gaussian `i` under `spec`.
    fn evaluate(&self, spec: &SceneSpec, i: usize) -> ([f32; 3], Slot, f32) {
        let object = self.labels.object[i];
        let part = self.labels.part[i];
        if object == FLOOR {
            let p = self.scene.mean(i);
            let tile = spec.floor.tile.max(1e-3);
            let parity =
                ((p[0] / tile).floor() as i64 + (p[1] / tile).floor() as i64).rem_euclid(2);
            return (spec.floor.colors[parity as usize], Slot::Fixed, 0.0);
        }
        if let Some(c) = part.fixed_color() {
            return (c, Slot::Fixed, 0.0);
        }
        let obj = if object == MAIN {
            &spec.main
        } else {
            match &spec.support {
                Some(t) => t,
                None => &spec.main,
            }
        };
        let mix = obj
            .pattern
            .mix(self.surface[i], &self.frames[object as usize]);
        let [a, b] = obj.colors.map(|c| c.rgb);
        let rgb = std::array::from_fn(|k| a[k] + (b[k] - a[k]) * mix);
        let slot = if mix < 0.5 { Slot::First } else { Slot::Second };
        (rgb, slot, mix)
    }

    fn paint(&mut self) {
        for i in 0..self.len() {
            let (rgb, slot, mix) = self.evaluate(&self.spec, i);
            for (k, c) in rgb.iter().enumerate() {
                self.scene.sh[3 * i + k] = (c - 0.5) / SH_C0;
            }
            self.labels.slot[i] = slot;
            self.labels.mix[i] = mix;
        }
    }
}

/// Number of channels of [`BuiltScene::label_channels`].
pub const LABEL_CHANNELS: usize = OBJECT_IDS + 3;

fn push_elements(
    scene: &mut GaussianScene,
    labels: &mut GaussianLabels,
    surface: &mut Vec<SurfacePoint>,
    elements: &[Element],
    object: u8,
    spacing: f32,
    settings: &BuildSettings,
) {
    let n = elements.len();
    scene.means.reserve(3 * n);
    scene.log_scales.reserve(3 * n);
    scene.quats.reserve(4 * n);
    scene.opacity_logits.reserve(n);
    scene.sh.reserve(3 * n);
    let opacity = settings.opacity.clamp(1e-3, 0.999);
    let logit = (opacity / (1.0 - opacity)).ln();
    let floor_sigma = 1e-4_f32.max(0.02 * spacing);
    for e in elements {
        let n = unit_or_z(Vec3::from(e.normal));
        // Re-orthogonalise the tangent against the normal (cheap insurance against rounding).
        let tangent = Vec3::from(e.tangent);
        let t1 = unit_or_z(tangent - tangent.dot(n) * n);
        let t2 = n.cross(t1);
        let s1 = (settings.overlap * e.extent[0]).max(floor_sigma);
        let s2 = (settings.overlap * e.extent[1]).max(floor_sigma);
        let sn = (settings.thickness * s1.min(s2)).max(1e-5);
        scene.means.extend_from_slice(&e.pos);
        scene
            .log_scales
            .extend_from_slice(&[s1.ln(), s2.ln(), sn.ln()]);
        scene
            .quats
            .extend_from_slice(&frame_quaternion(t1.into(), t2.into(), n.into()));
        scene.opacity_logits.push(logit);
        scene.sh.extend_from_slice(&[0.0; 3]);
        labels.object.push(object);
        labels.part.push(e.part);
        labels.slot.push(Slot::Fixed);
        labels.mix.push(0.0);
        surface.push(e.surface);
    }
}

/// The pattern frame of a shape: its reference circumference and the range of `v` over its patterned
/// elements.
fn pattern_frame(shape: &Shape, elements: &[Element]) -> PatternFrame {
    let mut lo = f32::INFINITY;
    let mut hi = f32::NEG_INFINITY;
    // The vase's inside continues the pattern but does not stretch the gradient over it.
    for e in elements
        .iter()
        .filter(|e| e.part.fixed_color().is_none() && e.part != Part::Inner)
    {
        lo = lo.min(e.surface.v);
        hi = hi.max(e.surface.v);
    }
    if !lo.is_finite() || !hi.is_finite() || hi <= lo {
        (lo, hi) = (0.0, 1.0);
    }
    PatternFrame {
        circumference: shape.circumference(),
        v_range: [lo, hi],
    }
}

/// The surface elements of a shape in object-local coordinates. Faces resting on the ground (a cylinder's
/// bottom, a cube's) are left out: no camera above the floor sees them, and their Gaussians' tails would
/// bleed out from under the object onto the floor.
pub(crate) fn object_elements<R: Rng>(
    shape: &Shape,
    spacing: f32,
    rng: &mut R,
    out: &mut Vec<Element>,
) {
    let arc = VMeasure::ArcLength;
    match *shape {
        Shape::Sphere { radius } => {
            revolve(
                &sphere_profile(0.0, radius, Part::Body),
                spacing,
                arc,
                rng,
                out,
            );
        }
        Shape::Cube { size } => box_faces(
            [0.5 * size; 2],
            [0.0, size],
            spacing,
            false,
            Part::Body,
            out,
        ),
        Shape::Cylinder { radius, height } => {
            let p = Profile::start([radius, 0.0])
                .line([radius, height], Part::Body)
                .line([0.0, height], Part::Body);
            revolve(&p, spacing, arc, rng, out);
        }
        Shape::Cone { radius, height } => {
            let p = Profile::start([radius, 0.0]).line([0.0, height], Part::Body);
            revolve(&p, spacing, arc, rng, out);
        }
        Shape::Torus { major, minor } => {
            let p = Profile::start([major, 0.0]).arc(
                [major, minor],
                [minor, minor],
                -FRAC_PI_2,
                1.5 * PI,
                Part::Body,
            );
            revolve(&p, spacing, arc, rng, out);
        }
        Shape::Vase { radius, height } => {
            // A bulging body that narrows to a neck, a rounded lip (a half torus), and the inside down to
            // a raised inner floor, so the opening looks hollow from above.
            let outer =
                move |z: f32| radius * (0.66 + 0.34 * (PI * (0.1 + 1.1 * z / height)).sin());
            let lip = VASE_LIP * radius;
            let neck = outer(height);
            let inner = move |z: f32| outer(z) - 2.0 * lip;
            let inner_floor = 0.12 * height;
            let p = Profile::start([outer(0.0), 0.0])
                .curve(outer, 0.0, height, Part::Body)
                .arc([neck - lip, height], [lip, lip], 0.0, PI, Part::Rim)
                .curve(inner, height, inner_floor, Part::Inner)
                .line([0.0, inner_floor], Part::Inner);
            revolve(&p, spacing, arc, rng, out);
        }
        Shape::Table {
            width,
            depth,
            height,
        } => {
            let top = TABLE_TOP.min(0.3 * height);
            box_faces(
                [0.5 * width, 0.5 * depth],
                [height - top, height],
                spacing,
                true,
                Part::Top,
                out,
            );
            let leg = TABLE_LEG.min(0.1 * depth);
            let p = Profile::start([leg, 0.0]).line([leg, height - top], Part::Leg);
            for (sx, sy) in [(1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)] {
                let start = out.len();
                revolve(&p, spacing, VMeasure::Height, rng, out);
                let m = Motion {
                    shift: [
                        sx * (0.5 * width - 2.0 * leg),
                        sy * (0.5 * depth - 2.0 * leg),
                        0.0,
                    ],
                    ..Motion::identity()
                };
                out[start..].iter_mut().for_each(|e| m.apply(e));
            }
        }
        Shape::Snowman { radius } => {
            let centres = snowman_centres(radius);
            for (k, c) in centres.iter().enumerate() {
                let r = SNOWMAN_RADII[k] * radius;
                revolve(
                    &sphere_profile(c - r, r, Part::Body),
                    spacing,
                    VMeasure::Height,
                    rng,
                    out,
                );
            }
            let head_r = SNOWMAN_RADII[2] * radius;
            let head_z = centres[2];
            // Carrot nose pointing along +x.
            let nose_len = 0.6 * head_r;
            let nose = Profile::start([0.0, 0.0])
                .line([0.14 * head_r, 0.0], Part::Nose)
                .line([0.0, nose_len], Part::Nose);
            let start = out.len();
            revolve(&nose, 0.5 * spacing, arc, rng, out);
            let m = Motion::z_to_x([0.9 * head_r, 0.0, head_z]);
            out[start..].iter_mut().for_each(|e| m.apply(e));
            // Two eyes above the nose.
            let eye_r = 0.11 * head_r;
            for side in [-1.0_f32, 1.0] {
                let (az, el) = (side * 0.42, 0.38_f32);
                let dir = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
                let start = out.len();
                revolve(
                    &sphere_profile(-eye_r, eye_r, Part::Eye),
                    0.5 * spacing,
                    arc,
                    rng,
                    out,
                );
                let shift = [
                    0.93 * head_r * dir[0],
                    0.93 * head_r * dir[1],
                    head_z + 0.93 * head_r * dir[2],
                ];
                let m = Motion {
                    shift,
                    ..Motion::identity()
                };
                out[start..].iter_mut().for_each(|e| m.apply(e));
            }
        }
        Shape::Mushroom {
            cap_radius,
            stem_height,
        } => {
            let stem_r = MUSHROOM_STEM_RADIUS * cap_radius;
            let stem = Profile::start([1.15 * stem_r, 0.0]).line([stem_r, stem_height], Part::Stem);
            revolve(&stem, spacing, arc, rng, out);
            let cap = Profile::start([0.0, stem_height])
                .line([cap_radius, stem_height], Part::Underside)
                .arc(
                    [0.0, stem_height],
                    [cap_radius, MUSHROOM_CAP_HEIGHT * cap_radius],
                    0.0,
                    FRAC_PI_2,
                    Part::Cap,
                );
            revolve(&cap, spacing, arc, rng, out);
        }
    }
}

/// A sphere of radius `r` whose lowest point is at height `base`, from the bottom pole to the top.
fn sphere_profile(base: f32, r: f32, part: Part) -> Profile {
    Profile::start([0.0, base]).arc([0.0, base + r], [r, r], -FRAC_PI_2, FRAC_PI_2, part)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::caption::Appearance;
    use crate::world::palette::ColorName;
    use crate::world::pattern::{Orientation, PatternKind};
    use crate::world::shape::ShapeKind;
    use crate::world::spec::GeneratorSettings;

    fn spec_of(shape: ShapeKind, pattern: PatternKind, on_table: bool, seed: u64) -> SceneSpec {
        let app = Appearance {
            shape,
            colors: [ColorName::Red, ColorName::Blue],
            pattern,
            on_table,
        };
        SceneSpec::from_appearance(&app, seed, &GeneratorSettings::default())
    }

    fn quat_norm(q: &[f32]) -> f32 {
        q.iter().map(|c| c * c).sum::<f32>().sqrt()
    }

    #[test]
    fn every_shape_builds_valid_gaussians_within_its_bounds() {
        let settings = BuildSettings::default();
        for shape in ShapeKind::ALL {
            for on_table in [false, true] {
                if on_table && !shape.can_stand_on_table() {
                    continue;
                }
                let spec = spec_of(shape, PatternKind::Stripes, on_table, 11);
                let built = build_scene(&spec, &settings);
                let s = &built.scene;
                s.check_shapes().unwrap();
                assert_eq!(built.labels.object.len(), s.len());
                assert!(s
                    .means
                    .iter()
                    .chain(&s.log_scales)
                    .chain(&s.quats)
                    .chain(&s.sh)
                    .all(|v| v.is_finite()));
                for q in s.quats.chunks_exact(4) {
                    assert!((quat_norm(q) - 1.0).abs() < 1e-4);
                }
                // Flat: the normal axis is the thinnest.
                for l in s.log_scales.chunks_exact(3) {
                    assert!(l[2] < l[0] && l[2] < l[1]);
                }
                let main: Vec<usize> = (0..s.len())
                    .filter(|&i| built.labels.object[i] == MAIN)
                    .collect();
                let count = main.len();
                assert!(
                    (1_000..40_000).contains(&count),
                    "{shape:?}: {count} Gaussians"
                );
                // Gaussians of the main object lie in its spec bounds (up to half a spacing), and reach
                // them (the bounds are tight).
                let (lo, hi) = spec.main.bounds();
                let tol = settings.spacing;
                let mut got_lo = [f32::INFINITY; 3];
                let mut got_hi = [f32::NEG_INFINITY; 3];
                for &i in &main {
                    let p = s.mean(i);
                    for a in 0..3 {
                        assert!(
                            p[a] >= lo[a] - tol && p[a] <= hi[a] + tol,
                            "{shape:?} axis {a}: {p:?} not in {lo:?}..{hi:?}"
                        );
                        got_lo[a] = got_lo[a].min(p[a]);
                        got_hi[a] = got_hi[a].max(p[a]);
                    }
                }
                let slack = if shape == ShapeKind::Snowman {
                    0.2
                } else {
                    0.05
                };
                for a in 0..3 {
                    let span = hi[a] - lo[a];
                    assert!(
                        got_hi[a] - got_lo[a] > (1.0 - slack) * span - 2.0 * tol,
                        "{shape:?} axis {a}"
                    );
                }
                // Both colours of the pattern are used.
                let firsts = main
                    .iter()
                    .filter(|&&i| built.labels.slot[i] == Slot::First)
                    .count();
                let seconds = main
                    .iter()
                    .filter(|&&i| built.labels.slot[i] == Slot::Second)
                    .count();
                assert!(
                    firsts > count / 8 && seconds > count / 8,
                    "{shape:?}: {firsts} / {seconds}"
                );
            }
        }
    }

    #[test]
    fn building_is_deterministic_and_density_follows_spacing() {
        let spec = spec_of(ShapeKind::Vase, PatternKind::Dots, true, 5);
        let a = build_scene(&spec, &BuildSettings::default());
        let b = build_scene(&spec, &BuildSettings::default());
        assert_eq!(a.scene, b.scene);
        assert_eq!(a.labels, b.labels);
        let coarse = build_scene(&spec, &BuildSettings::with_spacing(0.032));
        let ratio = a.len() as f32 / coarse.len() as f32;
        assert!(ratio > 3.3 && ratio < 4.7, "{ratio}");
        let other = build_scene(
            &spec_of(ShapeKind::Vase, PatternKind::Dots, true, 6),
            &BuildSettings::default(),
        );
        assert_ne!(a.scene.means, other.scene.means);
    }

    #[test]
    fn recolouring_matches_building_the_target_and_rejects_other_geometry() {
        let spec = spec_of(ShapeKind::Sphere, PatternKind::Stripes, false, 2);
        let target = spec.with_caption("a green checkered sphere").unwrap();
        let mut built = build_scene(&spec, &BuildSettings::default());
        let direct = build_scene(&target, &BuildSettings::default());
        let expected = built.colors_for(&target).unwrap();
        let max_diff = expected
            .iter()
            .zip(direct.colors())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(max_diff < 1e-5, "{max_diff}");
        built.recolor(&target).unwrap();
        assert!(
            built.scene == direct.scene,
            "recoloured scene differs from the directly built one"
        );
        assert!(built.labels == direct.labels);
        let other = spec_of(ShapeKind::Sphere, PatternKind::Stripes, false, 3);
        assert!(built.recolor(&other).is_err());
        assert!(built.colors_for(&other).is_err());
        // The colours are the spec's: main Gaussians show red or blue, the floor shows its tones.
        let colors = direct.colors();
        for i in 0..direct.len() {
            let c = &colors[3 * i..3 * i + 3];
            let expected = match (direct.labels.object[i], direct.labels.slot[i]) {
                (MAIN, Slot::First) => target.main.colors[0].rgb,
                (MAIN, Slot::Second) => target.main.colors[1].rgb,
                (FLOOR, _) => {
                    let f = target.floor.colors;
                    if (c[0] - f[0][0]).abs() < 1e-5 {
                        f[0]
                    } else {
                        f[1]
                    }
                }
                other => panic!("unexpected label {other:?}"),
            };
            for k in 0..3 {
                assert!((c[k] - expected[k]).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn two_phases_give_different_patterns() {
        for orientation in Orientation::ALL {
            let mut spec = spec_of(ShapeKind::Cylinder, PatternKind::Stripes, false, 9);
            spec.main.pattern.orientation = orientation;
            let mut shifted = spec.clone();
            // Half a period across the stripes swaps the colours.
            let axis = if orientation == Orientation::Vertical {
                0
            } else {
                1
            };
            shifted.main.pattern.phase[axis] += 0.5;
            let a = build_scene(&spec, &BuildSettings::default());
            let b = build_scene(&shifted, &BuildSettings::default());
            let main = (0..a.len()).filter(|&i| a.labels.object[i] == MAIN);
            let flipped = main
                .clone()
                .filter(|&i| a.labels.slot[i] != b.labels.slot[i])
                .count();
            assert!(
                flipped as f32 > 0.9 * main.count() as f32,
                "{orientation:?}"
            );
        }
    }

    #[test]
    fn fixed_parts_keep_their_colours() {
        let spec = spec_of(ShapeKind::Mushroom, PatternKind::Dots, false, 1);
        let built = build_scene(&spec, &BuildSettings::default());
        let stems = (0..built.len())
            .filter(|&i| built.labels.part[i] == Part::Stem)
            .count();
        assert!(stems > 100);
        for i in 0..built.len() {
            if built.labels.part[i] == Part::Stem {
                assert_eq!(built.labels.slot[i], Slot::Fixed);
            }
        }
        let snowman = build_scene(
            &spec_of(ShapeKind::Snowman, PatternKind::Solid, false, 1),
            &BuildSettings::default(),
        );
        for part in [Part::Nose, Part::Eye] {
            assert!(snowman.labels.part.contains(&part), "{part:?}");
        }
    }
}
