//! The one training loop step of every fit — the scene fit (`fit`), the editing fit and ECM's mini fits
//! (in `edit`): a step runs *resident* (scene, Adam moments, statistics, mask and anchors on the device,
//! [`DeviceTrainer`]) when the device can evaluate the loss and the step does not change the structure,
//! else on the *host* state (render, loss and backward still on the device when there is one), after
//! which the caller may densify. [`Trainer::sync`] brings the host state up to date.
//!
//! Clients own the schedule (which view, which rates, when the structure changes) and the strategy; the
//! trainer owns where and how a step runs.

use ::gpu::cubecl::server::Handle;
use ::gpu::F32Buffer;

use crate::cameras::Camera;
use crate::device::SplatDevice;
use crate::render::{FrozenGeometry, RenderSettings, SceneGrads};
use crate::scene::GaussianScene;
use crate::train::gpu::{DevicePair, DeviceTrainer, L1DssimWeights};
use crate::train::optim::Adam;
use crate::train::TrainState;
use ::gpu::{GpuContext, GpuError};

/// The image loss of a fit.
pub trait FitLoss {
    type Error: From<GpuError>;
    /// The value and its gradient with respect to `rgb` (H*W*3), the render of view `v`.
    fn eval(&mut self, rgb: &[f32], v: usize) -> Result<(f32, Vec<f32>), Self::Error>;
    /// The loss as `l1·L1 + dssim·D-SSIM` (plus [`FitLoss::device_term`]) when the device can evaluate
    /// it: the step then runs resident. `None`: host only (e.g. LPIPS on a CPU network).
    fn device_weights(&self) -> Option<L1DssimWeights>;
    /// A term the device adds to the `device_weights` loss (LPIPS on a network sharing the GPU): given the
    /// render of view `v` (H*W*3 f32 on the device) and the L1 + D-SSIM gradient w.r.t. it, the total
    /// gradient, also on the device. With `read_value`, the term's value is kept for
    /// [`FitLoss::take_device_value`]. The default adds nothing.
    fn device_term(
        &mut self,
        _rgb: &F32Buffer,
        grad: F32Buffer,
        _v: usize,
        _read_value: bool,
    ) -> Result<F32Buffer, Self::Error> {
        Ok(grad)
    }
    /// The value of the last [`FitLoss::device_term`] asked to read it (0 when there is no term).
    fn take_device_value(&mut self) -> f32 {
        0.0
    }
    /// Whether [`FitLoss::device_term`] adds a term (then two fits do not step together:
    /// [`PairTrainer`]). The default adds none.
    fn has_device_term(&self) -> bool {
        false
    }
}

/// What a step needs of the state's location.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StepKind {
    /// An ordinary step: resident when possible. `track_stats`: accumulate densification statistics
    /// (a host step hands the gradients to the caller instead); `read_loss`: read the loss value back
    /// (a copy from the device the editing fits skip).
    Ordinary { track_stats: bool, read_loss: bool },
    /// The caller changes or reads the structure after this step (densification, resets, evaluation):
    /// the state is synced first and the step runs on the host.
    Host,
}

/// Seconds spent in a host step's stages (the loss is evaluated on the host, so the render and its
/// read-back are before it and the backward pass after it).
#[derive(Clone, Copy, Debug, Default)]
pub struct StageSeconds {
    pub render: f64,
    pub loss: f64,
    pub backward: f64,
    pub optimise: f64,
}

/// What a step left for the caller.
// Returned by value once per step and consumed at once: boxing the gradients would cost more than the
// size difference.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub enum StepOutcome {
    /// Ran on the device state; the loss when it was read.
    Resident { loss: Option<f32> },
    /// Ran on the host state: the loss, the gradients (the anchor term included) and radii, for
    /// densification.
    Host {
        loss: f32,
        grads: SceneGrads,
        radii: Vec<u32>,
        seconds: StageSeconds,
    },
}

/// The device side of a fit whose loss the device evaluates: the targets, uploaded once, and the
/// resident state, built from the host state at the first resident step after a sync.
struct Resident {
    ctx: GpuContext,
    weights: L1DssimWeights,
    targets: Vec<Handle>,
    state: Option<DeviceTrainer>,
}

/// Runs the steps of one fit on a device (see the module documentation).
pub struct Trainer {
    device: SplatDevice,
    settings: RenderSettings,
    resident: Option<Resident>,
    /// Set by [`Trainer::freeze_geometry`]: the views' kept projections.
    frozen: Option<FrozenGeometry>,
}

impl Trainer {
    /// A fit to `targets` (one H*W*3 image per view) over `background` with `loss`.
    pub fn new<'t>(
        device: &SplatDevice,
        loss: &impl FitLoss,
        targets: impl IntoIterator<Item = &'t [f32]>,
        background: [f32; 3],
    ) -> Self {
        let resident = match (device.gpu(), loss.device_weights()) {
            (Some(ctx), Some(weights)) => Some(Resident {
                ctx: ctx.clone(),
                weights,
                targets: targets
                    .into_iter()
                    .map(|t| ::gpu::prims::upload_f32(&ctx.client, t))
                    .collect(),
                state: None,
            }),
            _ => None,
        };
        Self {
            device: device.clone(),
            settings: RenderSettings { background },
            resident,
            frozen: None,
        }
    }

    /// From now on the caller keeps the geometry (means, scales, rotations) fixed and needs no gradients
    /// for it, as ECM's appearance fits do: steps whose geometry rates are all zero reuse each view's
    /// projection and skip the geometry's backward pass (its gradients are zero; Adam then only decays
    /// those moments): host steps through [`FrozenGeometry`], resident ones through the device's kept
    /// views ([`DeviceTrainer::freeze_geometry`]). Steps with a geometry rate above zero run the full
    /// pass.
    pub fn freeze_geometry(&mut self) {
        self.frozen.get_or_insert_with(FrozenGeometry::default);
        if let Some(trainer) = self.resident.as_mut().and_then(|r| r.state.as_mut()) {
            trainer.freeze_geometry();
        }
    }

    /// One step on view `v` seen from `camera`. `state.adam` gives the rates (callers set its
    /// iteration) and counts the step; after a resident step `state` is stale until [`Trainer::sync`].
    pub fn step<L: FitLoss>(
        &mut self,
        state: &mut TrainState,
        camera: &Camera,
        v: usize,
        loss: &mut L,
        kind: StepKind,
    ) -> Result<StepOutcome, L::Error> {
        if let (
            Some(res),
            StepKind::Ordinary {
                track_stats,
                read_loss,
            },
        ) = (&mut self.resident, kind)
        {
            let ctx = &res.ctx;
            let trainer = match &mut res.state {
                Some(t) => t,
                None => {
                    let trainer = res.state.insert(DeviceTrainer::upload(ctx, state));
                    if self.frozen.is_some() {
                        trainer.freeze_geometry();
                    }
                    trainer
                }
            };
            let value = trainer.step_weighted(
                ctx,
                &mut state.adam,
                camera,
                v,
                &res.targets[v],
                &self.settings,
                res.weights,
                track_stats,
                |rgb, grad| loss.device_term(rgb, grad, v, read_loss),
            )?;
            let loss = if read_loss {
                Some(value.value(ctx)? + loss.take_device_value())
            } else {
                None
            };
            return Ok(StepOutcome::Resident { loss });
        }
        self.sync(state)?;
        let clock = std::time::Instant::now;
        let start = clock();
        let mut span = (start, start);
        let eval = |rgb: &[f32]| {
            let t = clock();
            let out = match loss.eval(rgb, v) {
                Ok((value, grad)) => (Ok(value), grad),
                // The backward still runs on a zero gradient; its result is dropped with the error.
                Err(e) => (Err(e), vec![0.0; rgb.len()]),
            };
            span = (t, clock());
            out
        };
        let (scene, settings) = (&state.scene, &self.settings);
        let (radii, value, mut grads) = match self.frozen.as_mut() {
            Some(frozen) if state.adam.geometry_fixed() => self
                .device
                .render_with_loss_frozen(scene, camera, v, frozen, settings, eval)?,
            _ => self
                .device
                .render_with_loss(scene, camera, settings, eval)?,
        };
        let value = value?;
        let backward_end = clock();
        if let Some(anchor) = &state.anchor {
            anchor.loss(&state.scene, state.trainable.as_deref(), Some(&mut grads));
        }
        state.step(&grads);
        let seconds = StageSeconds {
            render: (span.0 - start).as_secs_f64(),
            loss: (span.1 - span.0).as_secs_f64(),
            backward: (backward_end - span.1).as_secs_f64(),
            optimise: backward_end.elapsed().as_secs_f64(),
        };
        Ok(StepOutcome::Host {
            loss: value,
            grads,
            radii,
            seconds,
        })
    }

    /// Brings `state` up to date with the device; the next resident step re-uploads it (the host may
    /// change it in between).
    pub fn sync(&mut self, state: &mut TrainState) -> Result<(), GpuError> {
        if let Some(res) = &mut self.resident {
            if let Some(trainer) = res.state.take() {
                trainer.download_into(&res.ctx, state)?;
            }
        }
        Ok(())
    }
}

/// Two fits of copies of one state that keep its geometry, stepped together on a GPU: both fits' step
/// in one launch sequence, their views' kept projections shared (`train::gpu::pair`). ECM's target and
/// layout fits with their appearance alone. Each fit ends as the same fit alone through [`Trainer`]
/// would, up to the order in which the backward's atomics add.
pub struct PairTrainer {
    ctx: GpuContext,
    weights: L1DssimWeights,
    targets: [Vec<Handle>; 2],
    settings: RenderSettings,
    pair: DevicePair,
}

impl PairTrainer {
    /// Fits of two copies of `state` to `targets[0]` and `targets[1]` (one H*W*3 image per view of
    /// `cameras` each) over `background` with `loss`; `None` where they cannot step together: no GPU,
    /// a loss the device does not evaluate alone (host only, or with a device term), geometry rates
    /// above 0, anchors, or views of different sizes.
    pub fn new<'t, T: IntoIterator<Item = &'t [f32]>>(
        device: &SplatDevice,
        loss: &impl FitLoss,
        targets: [T; 2],
        cameras: &[Camera],
        background: [f32; 3],
        state: &TrainState,
    ) -> Option<Self> {
        let ctx = device.gpu()?;
        let weights = loss.device_weights()?;
        let one_size = cameras
            .windows(2)
            .all(|w| (w[0].width, w[0].height) == (w[1].width, w[1].height));
        let kept = state.adam.geometry_fixed() && state.anchor.is_none();
        if loss.has_device_term() || !one_size || !kept {
            return None;
        }
        let targets = targets.map(|set| {
            set.into_iter()
                .map(|t| ::gpu::prims::upload_f32(&ctx.client, t))
                .collect::<Vec<_>>()
        });
        Some(Self {
            ctx: ctx.clone(),
            weights,
            targets,
            settings: RenderSettings { background },
            pair: DevicePair::upload(ctx, state),
        })
    }

    /// One step of each fit: the first on view `views[0]` seen from `cameras[0]`, the second on
    /// `views[1]` from `cameras[1]`. `adam` gives both fits' rates (its geometry rates stay 0) and
    /// counts the step.
    pub fn step(
        &mut self,
        adam: &mut Adam,
        cameras: [&Camera; 2],
        views: [usize; 2],
    ) -> Result<(), GpuError> {
        let targets = [&self.targets[0][views[0]], &self.targets[1][views[1]]];
        self.pair.step(
            &self.ctx,
            adam,
            cameras,
            views,
            targets,
            &self.settings,
            self.weights,
        )
    }

    /// The two fitted scenes.
    pub fn finish(self) -> Result<[GaussianScene; 2], GpuError> {
        self.pair.download(&self.ctx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::gpu::tests::{camera, random_scene};
    use crate::render::render;
    use crate::train::optim::Group;
    use crate::train::optim::LearningRates;

    /// L1 to fixed targets.
    struct L1<'a>(&'a [Vec<f32>]);

    impl FitLoss for L1<'_> {
        type Error = GpuError;
        fn eval(&mut self, rgb: &[f32], v: usize) -> Result<(f32, Vec<f32>), GpuError> {
            let l = crate::train::loss::l1(rgb, &self.0[v]);
            Ok((l.value, l.grad))
        }
        fn device_weights(&self) -> Option<L1DssimWeights> {
            None
        }
    }

    /// An appearance fit with frozen geometry ends in the same scene, bit for bit, as the full passes;
    /// its steps give no geometry gradients, and a step with a geometry rate runs the full pass.
    #[test]
    fn frozen_geometry_fit_matches_the_full_fit() {
        let scene = random_scene(400, 2, 21);
        let cams: Vec<Camera> = [(40, 30), (44, 28), (36, 36)]
            .iter()
            .map(|&(w, h)| camera(w, h))
            .collect();
        let settings = RenderSettings {
            background: [0.3, 0.3, 0.3],
        };
        let mut target_scene = scene.clone();
        target_scene
            .sh
            .iter_mut()
            .step_by(3)
            .for_each(|v| *v += 0.8);
        let targets: Vec<Vec<f32>> = cams
            .iter()
            .map(|c| render(&target_scene, c, &settings, None).rgb.clone())
            .collect();
        let cpu_trainer = |loss: &L1| {
            let targets = targets.iter().map(|t| t.as_slice());
            Trainer::new(&SplatDevice::Cpu, loss, targets, settings.background)
        };
        let fit = |freeze: bool| {
            let mut state = TrainState::new(scene.clone(), LearningRates::inria(100), 1.0);
            state.trainable = Some((0..scene.len()).map(|i| i % 2 == 0).collect());
            for g in [Group::Means, Group::LogScales, Group::Quats] {
                state.adam.group_lr_scale[g.index()] = 0.0;
            }
            let mut loss = L1(&targets);
            let mut trainer = cpu_trainer(&loss);
            if freeze {
                trainer.freeze_geometry();
            }
            let kind = StepKind::Ordinary {
                track_stats: false,
                read_loss: false,
            };
            let mut geometry_grads = false;
            for step in 0..24 {
                let v = (step * 5) % cams.len();
                let out = trainer
                    .step(&mut state, &cams[v], v, &mut loss, kind)
                    .unwrap();
                let StepOutcome::Host { grads, .. } = out else {
                    panic!("a CPU step runs on the host")
                };
                geometry_grads |= grads.means.iter().any(|g| *g != 0.0);
            }
            (state, geometry_grads)
        };
        let (full, full_geometry) = fit(false);
        let (frozen, frozen_geometry) = fit(true);
        assert!(full_geometry && !frozen_geometry);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_ne!(
            bits(&full.scene.sh),
            bits(&scene.sh),
            "the fit moved the colours"
        );
        assert_eq!(bits(&full.scene.sh), bits(&frozen.scene.sh));
        assert_eq!(
            bits(&full.scene.opacity_logits),
            bits(&frozen.scene.opacity_logits)
        );
        assert_eq!(bits(&full.scene.means), bits(&frozen.scene.means));

        // With a position rate the frozen trainer runs the full pass.
        let mut state = TrainState::new(scene.clone(), LearningRates::inria(100), 1.0);
        let mut loss = L1(&targets);
        let mut trainer = cpu_trainer(&loss);
        trainer.freeze_geometry();
        let kind = StepKind::Ordinary {
            track_stats: false,
            read_loss: false,
        };
        let out = trainer
            .step(&mut state, &cams[0], 0, &mut loss, kind)
            .unwrap();
        let StepOutcome::Host { grads, .. } = out else {
            panic!("a CPU step runs on the host")
        };
        assert!(grads.means.iter().any(|g| *g != 0.0));
    }
}
