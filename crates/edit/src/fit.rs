//! Fitting Gaussians to edited images: the image loss of every fit and the editing loop's per-iteration fit
//! ([`EditTrainer`]). ECM's "mini-GS" fits start from the trainer's state with the same loss
//! (`consistency::ecm`).
//!
//! Losses (docs/algorithm.md §0, §1.3): 10·L1 + 10·LPIPS-VGG with user-supplied VGG weights; without them
//! 10·L1 + 2.5·D-SSIM, the INRIA trainer's L1 : D-SSIM ratio (0.8 : 0.2) scaled to the same L1 weight. The
//! editing fit adds the HGS anchor loss (VcEdit's weights) and GaussianEditor's mask-restricted
//! densification.

use std::path::Path;
use std::sync::Arc;

use diffusion::device::DeviceTensor;
use diffusion::lpips::{Lpips, LpipsError, LpipsTarget, TargetCache};
use gpu::{F32Buffer, GpuError};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use splat::train::anchor::{Anchor, AnchorConfig};
use splat::train::densify::EditStrategy;
use splat::train::loss;
use splat::train::optim::{Group, LearningRates};
use splat::train::{FitLoss, L1DssimWeights, StepKind, StepOutcome, Trainer};
use splat::train::{RenderedView, TrainState};
use splat::{Camera, GaussianScene, Image, SplatDevice};

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{0}")]
    Input(String),
    #[error("{}: {msg}", .path.display())]
    State {
        path: std::path::PathBuf,
        msg: String,
    },
    #[error(transparent)]
    Lpips(#[from] LpipsError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

/// The image loss of every fit.
pub enum ImageLoss {
    /// λ_L1·L1 + λ_LPIPS·LPIPS.
    Lpips { net: Lpips, l1: f32, lpips: f32 },
    /// λ_L1·L1 + λ_DSSIM·(1 − SSIM).
    Dssim { l1: f32, dssim: f32 },
}

impl ImageLoss {
    /// The reference's 10·L1 + 10·LPIPS.
    pub fn lpips(net: Lpips) -> Self {
        ImageLoss::Lpips {
            net,
            l1: 10.0,
            lpips: 10.0,
        }
    }

    /// The fallback without VGG weights: 10·L1 + 2.5·D-SSIM.
    pub fn dssim() -> Self {
        ImageLoss::Dssim {
            l1: 10.0,
            dssim: 2.5,
        }
    }

    pub fn describe(&self) -> String {
        match self {
            ImageLoss::Lpips { l1, lpips, .. } => format!("{l1}·L1 + {lpips}·LPIPS-VGG"),
            ImageLoss::Dssim { l1, dssim } => {
                format!("{l1}·L1 + {dssim}·D-SSIM (no LPIPS weights given)")
            }
        }
    }

    /// The loss as L1 and D-SSIM weights when the device evaluates it: L1 + D-SSIM always, L1 + LPIPS when
    /// the network runs on the GPU (its term comes from `Targets::device_term`).
    fn device_weights(&self) -> Option<L1DssimWeights> {
        match self {
            ImageLoss::Dssim { l1, dssim } => Some(L1DssimWeights::new(*l1, *dssim)),
            ImageLoss::Lpips { net, l1, .. } => {
                net.device().is_gpu().then(|| L1DssimWeights::new(*l1, 0.0))
            }
        }
    }

    /// GPU memory the loss itself holds during a fit of `views` views of `size` (width, height): LPIPS's
    /// activations and its cached target features when the network runs on a GPU; 0 otherwise (the
    /// renderer's buffers, L1 + D-SSIM's included, are in the run's own estimate).
    pub fn gpu_bytes(&self, size: (u32, u32), views: usize) -> u64 {
        match self {
            ImageLoss::Lpips { net, .. } if net.device().is_gpu() => {
                let (w, h) = (size.0 as usize, size.1 as usize);
                let targets = net.target_bytes(h, w).saturating_mul(views);
                (net.activation_bytes(h, w) + targets.min(LPIPS_CACHE_BYTES)) as u64
            }
            _ => 0,
        }
    }

    /// Loss value and gradient w.r.t. the render (H*W*3) of view `v` against its target.
    fn eval(
        &self,
        render: &[f32],
        v: usize,
        targets: &mut Targets<'_>,
    ) -> Result<(f32, Vec<f32>), TrainError> {
        let images = targets.images;
        let target = &images[v];
        let (w, h) = (target.width as usize, target.height as usize);
        let l1 = loss::l1(render, &target.data);
        match self {
            ImageLoss::Lpips {
                net,
                l1: wl1,
                lpips: wl,
            } => {
                let features = targets.lpips_features(net, v)?;
                let p = net.loss_and_grad(render, h, w, &features)?;
                let grad = l1
                    .grad
                    .iter()
                    .zip(&p.grad)
                    .map(|(a, b)| wl1 * a + wl * b)
                    .collect();
                Ok((wl1 * l1.value + wl * p.value, grad))
            }
            ImageLoss::Dssim { l1: wl1, dssim: wd } => {
                let s = match targets.ssim_target(v) {
                    Some(t) => loss::ssim_to(render, t),
                    None => loss::ssim(render, &target.data, w, h, 3),
                };
                let grad = l1
                    .grad
                    .iter()
                    .zip(&s.grad)
                    .map(|(a, b)| wl1 * a - wd * b)
                    .collect();
                Ok((wl1 * l1.value + wd * (1.0 - s.value), grad))
            }
        }
    }
}

/// Knobs of the editing fit.
#[derive(Clone, Debug, Serialize)]
pub struct TrainSettings {
    /// Steps over the whole edit (iterations × fit steps): the horizon of the position-rate schedule.
    pub total_steps: u64,
    /// Use the HGS anchor loss (VcEdit's weights).
    pub anchor: bool,
    #[serde(skip)]
    pub strategy: EditStrategy,
}

impl TrainSettings {
    pub fn new(total_steps: u64) -> Self {
        Self {
            total_steps,
            anchor: true,
            strategy: EditStrategy {
                // GaussianEditor's max_grad = 5 is compared with viewspace gradients still multiplied by
                // the AMP loss scale (2^16 at the start), i.e. ≈ 7.6e-5 unscaled: with the top-1% cut
                // (max_densify_percent) this densifies the masked Gaussians with the largest gradients.
                max_grad: 5.0 / 65536.0,
                ..EditStrategy::default()
            },
        }
    }
}

/// Memory for cached LPIPS target features (recomputed on a miss): VGG features of a 512² image take
/// ~130 MB, so at most about a dozen views' are kept.
pub const LPIPS_CACHE_BYTES: usize = 1_500_000_000;

/// Memory for the D-SSIM targets' statistics a fit keeps ([`loss::SsimTarget`], 36 bytes per pixel: all
/// 16 views of the demo at 128² take 9.4 MB, 27 views at 512²; views beyond it are blurred at each step).
pub const SSIM_CACHE_BYTES: usize = 256 << 20;

/// A fit's loss with its target images and cached loss precomputations.
pub(crate) struct Targets<'a> {
    loss: &'a ImageLoss,
    images: &'a [Image],
    cache: TargetCache,
    /// D-SSIM's target statistics by view, made at a view's first step while within
    /// [`SSIM_CACHE_BYTES`] (the same loss either way, bit for bit).
    ssim: Vec<Option<loss::SsimTarget>>,
    ssim_bytes: usize,
    /// The cache's entries by view. A fit's target images never change, so a view the cache holds is
    /// taken from here without fingerprinting its pixels again: that reads the whole image, which a
    /// resident step on a GPU would otherwise do on the CPU every step.
    kept: Vec<Option<Arc<LpipsTarget>>>,
    /// The weighted LPIPS of the last device step that read its value.
    device_value: f32,
}

impl<'a> Targets<'a> {
    pub(crate) fn new(loss: &'a ImageLoss, images: &'a [Image]) -> Self {
        Self {
            loss,
            images,
            cache: TargetCache::new(LPIPS_CACHE_BYTES),
            kept: vec![None; images.len()],
            ssim: vec![None; images.len()],
            ssim_bytes: 0,
            device_value: 0.0,
        }
    }

    /// View `v`'s D-SSIM target statistics: kept from an earlier step, else made now when the budget
    /// allows (`None`: it does not, compute them with the loss).
    fn ssim_target(&mut self, v: usize) -> Option<&loss::SsimTarget> {
        if self.ssim[v].is_none() {
            let t = &self.images[v];
            let (w, h, ch) = (t.width as usize, t.height as usize, t.channels as usize);
            let bytes = loss::SsimTarget::bytes_for(w, h, ch);
            if self.ssim_bytes + bytes > SSIM_CACHE_BYTES {
                return None;
            }
            self.ssim[v] = Some(loss::SsimTarget::new(&t.data, w, h, ch));
            self.ssim_bytes += bytes;
        }
        self.ssim[v].as_ref()
    }

    /// The LPIPS features of view `v`'s target image.
    fn lpips_features(&mut self, net: &Lpips, v: usize) -> Result<Arc<LpipsTarget>, LpipsError> {
        if let Some(features) = &self.kept[v] {
            return Ok(features.clone());
        }
        let target = &self.images[v];
        let (w, h) = (target.width as usize, target.height as usize);
        let features = self.cache.get_or_compute(net, v, &target.data, h, w)?;
        if self.cache.holds(v) {
            self.kept[v] = Some(features.clone());
        }
        Ok(features)
    }

    /// A trainer for a fit to these targets on `device`.
    pub(crate) fn trainer(&self, device: &SplatDevice, background: [f32; 3]) -> Trainer {
        Trainer::new(
            device,
            self,
            self.images.iter().map(|t| t.data.as_slice()),
            background,
        )
    }
}

impl FitLoss for Targets<'_> {
    type Error = TrainError;

    fn eval(&mut self, rgb: &[f32], v: usize) -> Result<(f32, Vec<f32>), TrainError> {
        let loss = self.loss;
        loss.eval(rgb, v, self)
    }

    fn device_weights(&self) -> Option<L1DssimWeights> {
        self.loss.device_weights()
    }

    fn has_device_term(&self) -> bool {
        matches!(self.loss, ImageLoss::Lpips { net, .. } if net.device().is_gpu())
    }

    /// λ·LPIPS of the render on the GPU the network shares with the renderer: the render and the
    /// gradients never leave the device (the value only when asked).
    fn device_term(
        &mut self,
        rgb: &F32Buffer,
        grad: F32Buffer,
        v: usize,
        read_value: bool,
    ) -> Result<F32Buffer, TrainError> {
        let ImageLoss::Lpips { net, lpips: wl, .. } = self.loss else {
            return Ok(grad);
        };
        if !net.device().is_gpu() {
            return Ok(grad);
        }
        let target = &self.images[v];
        let (w, h) = (target.width as usize, target.height as usize);
        let features = self.lpips_features(net, v)?;
        let compute_error = |cause| LpipsError::Compute {
            device: net.device().describe(),
            cause,
        };
        let on_device = |buffer: F32Buffer| {
            DeviceTensor::from_gpu_buffer(net.device(), buffer, vec![h * w * 3])
                .map_err(compute_error)
        };
        let out = net.loss_and_grad_on(&on_device(rgb.clone())?, h, w, &features)?;
        let weighted = out.grad.mul_scalar(f64::from(*wl)).map_err(compute_error)?;
        let total = on_device(grad)?.add(&weighted).map_err(compute_error)?;
        if read_value {
            self.device_value = wl * out.per_layer()?.iter().sum::<f32>();
        }
        Ok(total.into_gpu_buffer().map_err(compute_error)?)
    }

    fn take_device_value(&mut self) -> f32 {
        std::mem::take(&mut self.device_value)
    }
}

pub(crate) fn check_targets(cameras: &[Camera], targets: &[Image]) -> Result<(), TrainError> {
    if cameras.len() != targets.len() || cameras.is_empty() {
        return Err(TrainError::Input(format!(
            "{} targets for {} cameras",
            targets.len(),
            cameras.len()
        )));
    }
    for (c, t) in cameras.iter().zip(targets) {
        if (c.width, c.height, t.channels) != (t.width, t.height, 3) {
            return Err(TrainError::Input(format!(
                "target for camera {} is {}x{}x{}, expected {}x{}x3",
                c.name, t.width, t.height, t.channels, c.width, c.height
            )));
        }
    }
    Ok(())
}

/// The next view of a fit: views are drawn without replacement and reshuffled when exhausted.
fn next_view(order: &mut Vec<usize>, views: usize, rng: &mut ChaCha8Rng) -> usize {
    if order.is_empty() {
        *order = (0..views).collect();
        order.shuffle(rng);
    }
    order.pop().expect("refilled")
}

/// The editing loop's fit: GaussianEditor's optimiser, anchors and mask-restricted densification.
pub struct EditTrainer {
    pub state: TrainState,
    pub settings: TrainSettings,
    /// Steps taken over the whole edit (GaussianEditor's global step).
    pub global_step: u64,
    /// Background of the renders fitted (the targets' background).
    pub background: [f32; 3],
    /// Where the fit runs (`None`: the CPU). With the D-SSIM loss the scene, Adam moments, statistics,
    /// mask and anchors stay on the device between densifications (`DeviceTrainer` in splat); with
    /// LPIPS (a CPU network) only renders and their backward run there.
    pub device: SplatDevice,
}

impl EditTrainer {
    pub fn new(
        scene: &GaussianScene,
        mask: Option<Vec<bool>>,
        settings: TrainSettings,
        extent: f32,
        background: [f32; 3],
    ) -> Self {
        let mut state = TrainState::new(
            scene.clone(),
            LearningRates::gaussian_editor(settings.total_steps),
            extent,
        );
        state.trainable = mask;
        // GaussianEditor leaves rotations of frozen Gaussians unhooked (docs/algorithm.md §3.3), so they
        // drift outside the mask; an edit must not touch what the user excluded, so we freeze them too.
        state.adam.mask_rotation = true;
        if settings.anchor {
            state.anchor = Some(Anchor::new(scene, AnchorConfig::vcedit()));
        }
        Self {
            state,
            settings,
            global_step: 0,
            background,
            device: SplatDevice::Cpu,
        }
    }

    pub fn scene(&self) -> &GaussianScene {
        &self.state.scene
    }

    /// Sets the factor on the position, scale and rotation rates of the fits that follow (1: the
    /// reference's rates; `run::shape` keeps the geometry of appearance edits at a tenth).
    pub fn set_geometry_rate(&mut self, rate: f32) {
        for g in [Group::Means, Group::LogScales, Group::Quats] {
            self.state.adam.group_lr_scale[g.index()] = rate;
        }
    }

    /// Fits to one target per camera for `steps` single-view steps (views drawn without replacement,
    /// reshuffled when exhausted). `on_step(1)` after each step.
    pub fn fit(
        &mut self,
        cameras: &[Camera],
        targets: &[Image],
        steps: usize,
        loss: &ImageLoss,
        seed: u64,
        on_step: &mut dyn FnMut(u64),
    ) -> Result<(), TrainError> {
        check_targets(cameras, targets)?;
        let mut prepared = Targets::new(loss, targets);
        let mut trainer = prepared.trainer(&self.device, self.background);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut order: Vec<usize> = Vec::new();
        let mut run = || {
            for _ in 0..steps {
                let v = next_view(&mut order, cameras.len(), &mut rng);
                self.step(&mut trainer, &cameras[v], v, &mut prepared, &mut rng)?;
                on_step(1);
            }
            Ok::<_, TrainError>(())
        };
        let result = run();
        // The state is up to date on return (after a device error it holds the last synced state; the
        // run is over then anyway).
        let synced = trainer.sync(&mut self.state);
        result?;
        Ok(synced?)
    }

    /// One step of the editing fit on view `v`: resident on a device between densifications (the anchor
    /// gradient, the trainable mask and the statistics there too); a densification step runs on the host
    /// state, followed by GaussianEditor's densification.
    fn step(
        &mut self,
        trainer: &mut Trainer,
        camera: &Camera,
        v: usize,
        targets: &mut Targets<'_>,
        rng: &mut ChaCha8Rng,
    ) -> Result<(), TrainError> {
        let strategy = &self.settings.strategy;
        let kind = if strategy.densifies_at(self.global_step) {
            StepKind::Host
        } else {
            StepKind::Ordinary {
                track_stats: strategy.tracks_stats_at(self.global_step),
                read_loss: false,
            }
        };
        self.state.adam.set_iteration(self.global_step);
        if let StepOutcome::Host { grads, radii, .. } =
            trainer.step(&mut self.state, camera, v, targets, kind)?
        {
            self.settings.strategy.after_backward(
                &mut self.state,
                self.global_step,
                &RenderedView::new(&grads, &radii, camera),
                rng,
            );
        }
        self.global_step += 1;
        Ok(())
    }

    /// Saves the state that is not the scene itself (optimiser moments, statistics, mask, anchors, step).
    pub fn save(&self, path: &Path) -> Result<(), TrainError> {
        let bytes = self
            .state
            .to_bytes(self.global_step)
            .map_err(|msg| TrainError::State {
                path: path.into(),
                msg,
            })?;
        files::atomic_write(path, &bytes).map_err(|e| TrainError::State {
            path: path.into(),
            msg: e.to_string(),
        })
    }

    /// Restores a trainer saved by [`EditTrainer::save`] around `scene`.
    pub fn load(
        path: &Path,
        scene: &GaussianScene,
        settings: TrainSettings,
        extent: f32,
        background: [f32; 3],
    ) -> Result<Self, TrainError> {
        let bytes = std::fs::read(path).map_err(|e| TrainError::State {
            path: path.into(),
            msg: e.to_string(),
        })?;
        let rates = LearningRates::gaussian_editor(settings.total_steps);
        let (state, global_step) = TrainState::from_bytes(&bytes, scene.clone(), rates, extent)
            .map_err(|msg| TrainError::State {
                path: path.into(),
                msg,
            })?;
        Ok(Self {
            state,
            settings,
            global_step,
            background,
            device: SplatDevice::Cpu,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use splat::render::{render, RenderSettings};
    use splat::train::densify::EditStrategy;

    /// A 7³ box of Gaussians with position-dependent colours, two sizes (so densification both clones
    /// and splits) and SH degree 1.
    fn blob(shift: f32) -> GaussianScene {
        let mut s = GaussianScene::new(1);
        let n = 7;
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    let p = [i, j, k].map(|v| v as f32 / (n - 1) as f32 - 0.5 + shift);
                    s.means.extend_from_slice(&p);
                    let size = if (i + j + k) % 2 == 0 { 0.015f32 } else { 0.07 };
                    s.log_scales.extend_from_slice(&[size.ln(); 3]);
                    s.quats.extend_from_slice(&[1.0, 0.1 * p[0], 0.0, 0.0]);
                    s.opacity_logits.push(2.0);
                    let c = [
                        0.5 + 0.4 * (6.0 * p[0]).sin(),
                        0.5 + 0.4 * (5.0 * p[1] + shift * 20.0).cos(),
                        0.5 + 0.4 * p[2],
                    ];
                    s.sh.extend(c.iter().map(|v| (v - 0.5) / 0.282_094_8));
                    s.sh.extend((0..9).map(|e| 0.05 * ((e as f32) * p[1]).sin()));
                }
            }
        }
        s
    }

    /// The blob, three 40² views of a shifted copy as targets, and a mask freezing the left three
    /// columns of Gaussians.
    fn fixture() -> (GaussianScene, Vec<Camera>, Vec<Image>, Vec<bool>) {
        let scene = blob(0.0);
        let cams = splat::cameras::orbit_cameras([-0.5; 3], [0.5; 3], 3, 40, 40);
        let target_scene = blob(0.03);
        let targets: Vec<Image> = cams
            .iter()
            .map(|c| render(&target_scene, c, &RenderSettings::default(), None).rgb_image())
            .collect();
        let mask: Vec<bool> = (0..scene.len())
            .map(|j| scene.means[3 * j] > -0.1)
            .collect();
        (scene, cams, targets, mask)
    }

    fn trainer(scene: &GaussianScene, mask: &[bool]) -> EditTrainer {
        let mut settings = TrainSettings::new(100);
        // A densification at global step 5, with enough candidates to change the counts.
        settings.strategy = EditStrategy {
            densify_from: 5,
            interval: 5,
            max_densify_percent: 0.2,
            max_grad: 1e-9,
            ..settings.strategy
        };
        EditTrainer::new(scene, Some(mask.to_vec()), settings, 2.0, [0.0; 3])
    }

    /// The Gaussians `mask` leaves out, as one vector of all their parameters.
    fn frozen(s: &GaussianScene, mask: &[bool]) -> Vec<f32> {
        let k3 = 3 * s.sh_coeffs();
        let mut out = Vec::new();
        for j in (0..s.len()).filter(|&j| !mask[j]) {
            out.extend(&s.means[3 * j..3 * j + 3]);
            out.extend(&s.log_scales[3 * j..3 * j + 3]);
            out.extend(&s.quats[4 * j..4 * j + 4]);
            out.push(s.opacity_logits[j]);
            out.extend(&s.sh[k3 * j..k3 * (j + 1)]);
        }
        out
    }

    /// ‖a − b‖ / ‖b‖ over every parameter.
    fn rel_diff(a: &GaussianScene, b: &GaussianScene) -> f64 {
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for (x, y) in [
            (&a.means, &b.means),
            (&a.log_scales, &b.log_scales),
            (&a.quats, &b.quats),
            (&a.opacity_logits, &b.opacity_logits),
            (&a.sh, &b.sh),
        ] {
            assert_eq!(x.len(), y.len());
            for (p, q) in x.iter().zip(y) {
                num += ((p - q) as f64).powi(2);
                den += (*q as f64).powi(2);
            }
        }
        (num / den).sqrt()
    }

    /// The mean editing loss of `scene` over the views (on the CPU).
    fn mean_loss(scene: &GaussianScene, cams: &[Camera], targets: &[Image]) -> f32 {
        let loss = ImageLoss::dssim();
        let mut prepared = Targets::new(&loss, targets);
        let settings = RenderSettings::default();
        let sum: f32 = cams
            .iter()
            .enumerate()
            .map(|(v, c)| {
                let out = render(scene, c, &settings, None);
                prepared.eval(&out.rgb, v).unwrap().0
            })
            .sum();
        sum / cams.len() as f32
    }

    /// Device and host trainers agree: parameters within 1e-3 (relative), mean loss within
    /// `loss_tol` (relative).
    fn assert_close(
        dev: &EditTrainer,
        host: &EditTrainer,
        cams: &[Camera],
        targets: &[Image],
        loss_tol: f32,
        when: &str,
    ) {
        let e = rel_diff(dev.scene(), host.scene());
        let l_dev = mean_loss(dev.scene(), cams, targets);
        let l_host = mean_loss(host.scene(), cams, targets);
        eprintln!(
            "{when}: parameters differ by {e} (relative); loss host {l_host}, device {l_dev}"
        );
        assert!(e < 1e-3, "{when}: parameters differ by {e}");
        assert!(
            (l_dev - l_host).abs() < loss_tol * l_host,
            "{when}: loss {l_dev} vs {l_host}"
        );
    }

    /// A fit with LPIPS on the GPU (network and renderer there) follows the same fit on the CPU: the
    /// network runs where the fit renders, and both steer the scene alike.
    #[test]
    fn an_lpips_fit_on_the_gpu_tracks_the_cpu_fit() {
        let Some(ctx) = ::gpu::testing::context_or_skip() else {
            return;
        };
        let (scene, cams, targets, mask) = fixture();
        let net = || Lpips::synthetic([4, 6, 8, 8, 10], 7);
        let cpu_loss = ImageLoss::lpips(net());
        let gpu_loss = ImageLoss::lpips(net().on(diffusion::device::Device::Gpu(
            diffusion::device::GpuDevice::new(ctx.clone()),
        )));
        // On the GPU the step runs resident, LPIPS added by `Targets::device_term`; its memory is there.
        assert!(cpu_loss.device_weights().is_none() && gpu_loss.device_weights().is_some());
        assert_eq!(cpu_loss.gpu_bytes((40, 40), 3), 0);
        assert!(gpu_loss.gpu_bytes((40, 40), 3) > gpu_loss.gpu_bytes((40, 40), 1));
        let mut host = trainer(&scene, &mask);
        let mut dev = trainer(&scene, &mask);
        dev.device = SplatDevice::Gpu(ctx);

        // A resident step that reads its loss reports the host's value for the same render.
        let mut on_gpu = Targets::new(&gpu_loss, &targets);
        let mut fit = on_gpu.trainer(&dev.device, [0.0; 3]);
        let mut state = dev.state.clone();
        let kind = StepKind::Ordinary {
            track_stats: false,
            read_loss: true,
        };
        let StepOutcome::Resident {
            loss: Some(resident),
        } = fit
            .step(&mut state, &cams[0], 0, &mut on_gpu, kind)
            .unwrap()
        else {
            panic!("an LPIPS step on the GPU runs resident and reads its loss");
        };
        let rgb = render(&scene, &cams[0], &RenderSettings::default(), None)
            .into_frame()
            .rgb;
        let (host_value, _) = Targets::new(&cpu_loss, &targets).eval(&rgb, 0).unwrap();
        assert!(
            (resident - host_value).abs() < 1e-4 * host_value,
            "resident loss {resident} vs host {host_value}"
        );

        host.fit(&cams, &targets, 4, &cpu_loss, 1, &mut |_| {})
            .unwrap();
        dev.fit(&cams, &targets, 4, &gpu_loss, 1, &mut |_| {})
            .unwrap();
        assert!(rel_diff(host.scene(), &scene) > 1e-4, "the fit must move");
        let e = rel_diff(dev.scene(), host.scene());
        assert!(e < 1e-3, "GPU and CPU LPIPS fits differ by {e}");
    }

    /// The device editing fit (state on the device between densifications) follows the host fit from the
    /// same state and seeds: frozen Gaussians untouched, trainable ones close before the densification,
    /// the same counts after it, and the same loss.
    #[test]
    fn device_editing_fit_tracks_the_host_fit() {
        let Some(ctx) = ::gpu::testing::context_or_skip() else {
            return;
        };
        let (scene, cams, targets, mask) = fixture();
        let loss = ImageLoss::dssim();
        let mut host = trainer(&scene, &mask);
        let mut dev = trainer(&scene, &mask);
        dev.device = SplatDevice::Gpu(ctx);
        let start_loss = mean_loss(&scene, &cams, &targets);

        // Five steps (global 0..4): no densification yet.
        for t in [&mut host, &mut dev] {
            t.fit(&cams, &targets, 5, &loss, 1, &mut |_| {}).unwrap();
        }
        assert_eq!(dev.global_step, 5);
        assert_eq!(dev.state.adam.steps(), host.state.adam.steps());
        assert_eq!(frozen(dev.scene(), &mask), frozen(&scene, &mask));
        assert_eq!(frozen(host.scene(), &mask), frozen(&scene, &mask));
        assert!(rel_diff(host.scene(), &scene) > 1e-4, "the fit must move");
        eprintln!("loss before: {start_loss}");
        assert_close(&dev, &host, &cams, &targets, 1e-4, "after 5 steps");
        let stats = (&dev.state.stats.grad2d, &host.state.stats.grad2d);
        assert_eq!(dev.state.stats.count, host.state.stats.count);
        let num: f64 = stats
            .0
            .iter()
            .zip(stats.1)
            .map(|(a, b)| ((a - b) as f64).powi(2))
            .sum();
        let den: f64 = stats.1.iter().map(|b| (*b as f64).powi(2)).sum();
        assert!((num / den).sqrt() < 1e-3, "densification statistics differ");

        // Five more (global 5..9): densification at 5 on the host, then the device again.
        for t in [&mut host, &mut dev] {
            t.fit(&cams, &targets, 5, &loss, 2, &mut |_| {}).unwrap();
        }
        assert!(
            host.state.len() > scene.len(),
            "densification must add Gaussians"
        );
        assert_eq!(dev.state.len(), host.state.len());
        dev.state.check().unwrap();
        let dev_mask = dev.state.trainable.clone().unwrap();
        assert_eq!(&dev_mask, host.state.trainable.as_ref().unwrap());
        assert_eq!(frozen(dev.scene(), &dev_mask), frozen(&scene, &mask));
        let when = format!(
            "after 10 steps ({} → {} Gaussians)",
            scene.len(),
            dev.state.len()
        );
        assert_close(&dev, &host, &cams, &targets, 1e-3, &when);
    }

    /// ECM's mini-GS fit on the device (appearance only, masked) follows the host's: frozen Gaussians and
    /// geometry untouched, colours and opacities close.
    #[test]
    fn device_ecm_fit_tracks_the_host_fit() {
        use crate::consistency::{EcmFitter, EcmSettings, SceneFitter};
        let Some(ctx) = ::gpu::testing::context_or_skip() else {
            return;
        };
        let (scene, cams, targets, mask) = fixture();
        let loss = ImageLoss::dssim();
        let ecm = EcmSettings {
            min_steps: 9,
            epochs: 3,
            halve_every: 1,
            ..EcmSettings::reference(0)
        };
        let host = trainer(&scene, &mask);
        let mut dev = trainer(&scene, &mask);
        dev.device = SplatDevice::Gpu(ctx);
        let fit = |t: &EditTrainer| EcmFitter::new(t, &loss, &ecm).fit(&scene, &cams, &targets, 4);
        let (on_host, on_device) = (fit(&host).unwrap(), fit(&dev).unwrap());
        assert_eq!(frozen(&on_device, &mask), frozen(&scene, &mask));
        assert_eq!(on_device.means, scene.means);
        assert_eq!(on_device.log_scales, scene.log_scales);
        assert!(rel_diff(&on_host, &scene) > 1e-4, "the fit must move");
        let e = rel_diff(&on_device, &on_host);
        eprintln!("ECM fit, 9 steps: relative difference {e}");
        assert!(e < 1e-3, "ECM fit: {e}");
    }

    /// Times the editing fit step (no densification) on the CPU, with only the render and its backward
    /// on the device (the path before the state moved there; LPIPS still takes it), and with the state
    /// on the device. A measurement, not a check: `cargo test -p vcedit-edit --release --lib --
    /// --ignored time_editing_fit_step --nocapture` (`VCEDIT_TIME_N` Gaussians, `VCEDIT_TIME_SIZE` px).
    #[test]
    #[ignore]
    fn time_editing_fit_step() {
        let Some(ctx) = ::gpu::testing::context_or_skip() else {
            return;
        };
        let env = |name: &str, default: usize| {
            std::env::var(name)
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(default)
        };
        let (n, size, steps) = (env("VCEDIT_TIME_N", 4000), env("VCEDIT_TIME_SIZE", 128), 8);
        // Random Gaussians in a unit box, as the edit tests' blobs.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut scene = GaussianScene::new(1);
        for _ in 0..n {
            use rand::Rng;
            let p: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-0.5..0.5));
            scene.means.extend_from_slice(&p);
            scene.log_scales.extend_from_slice(&[(0.04f32).ln(); 3]);
            scene.quats.extend_from_slice(&[1.0, 0.1 * p[0], 0.0, 0.0]);
            scene.opacity_logits.push(2.0);
            scene.sh.extend(p.map(|v| v * 2.0));
            scene.sh.extend(std::iter::repeat_n(0.0, 9));
        }
        let cams = splat::cameras::orbit_cameras([-0.5; 3], [0.5; 3], 4, size as u32, size as u32);
        let mut shifted = scene.clone();
        shifted.sh.iter_mut().step_by(12).for_each(|v| *v += 0.3);
        let targets: Vec<Image> = cams
            .iter()
            .map(|c| render(&shifted, c, &RenderSettings::default(), None).rgb_image())
            .collect();
        let mask: Vec<bool> = (0..n).map(|j| scene.means[3 * j] > 0.0).collect();
        let loss = ImageLoss::dssim();
        let mut settings = TrainSettings::new(1000);
        settings.strategy.densify_from = u64::MAX;
        let make = |device: SplatDevice| {
            let mut t =
                EditTrainer::new(&scene, Some(mask.clone()), settings.clone(), 2.0, [0.0; 3]);
            t.device = device;
            t
        };
        let time = |label: &str, run: &mut dyn FnMut(usize)| {
            run(1); // warm-up: kernel compilation, first uploads
            let t = std::time::Instant::now();
            run(steps);
            let ms = t.elapsed().as_secs_f64() * 1e3 / steps as f64;
            eprintln!("{n} Gaussians, {size}²: {label}: {ms:.1} ms/step");
        };
        let mut cpu = make(SplatDevice::Cpu);
        time("CPU", &mut |k| {
            cpu.fit(&cams, &targets, k, &loss, 1, &mut |_| {}).unwrap()
        });
        let mut split = make(SplatDevice::Gpu(ctx.clone()));
        let mut prepared = Targets::new(&loss, &targets);
        let mut trainer = prepared.trainer(&split.device, split.background);
        let mut order = Vec::new();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        time(
            "render+backward on the device, the rest on the host",
            &mut |k| {
                for _ in 0..k {
                    let v = next_view(&mut order, cams.len(), &mut rng);
                    trainer
                        .step(&mut split.state, &cams[v], v, &mut prepared, StepKind::Host)
                        .unwrap();
                }
            },
        );
        // The loss alone (the part that moves from the host to the device).
        let (a, b) = (&targets[0].data, &targets[1].data);
        time("loss alone on the host", &mut |k| {
            for _ in 0..k {
                std::hint::black_box(prepared.eval(a, 1).map(|(v, _)| v).unwrap());
            }
        });
        let up = |v: &[f32]| ::gpu::prims::upload_f32(&ctx.client, v);
        let (a, b) = (up(a), up(b));
        let weights = L1DssimWeights::new(10.0, 2.5);
        time("loss alone on the device", &mut |k| {
            for _ in 0..k {
                let l =
                    splat::stages::l1_dssim_weighted(&ctx, &a, &b, size, size, 3, weights).unwrap();
                std::hint::black_box(l.value(&ctx).unwrap());
            }
        });
        let mut dev = make(SplatDevice::Gpu(ctx.clone()));
        time(
            "state on the device (per fit call: one upload, one download)",
            &mut |k| dev.fit(&cams, &targets, k, &loss, 1, &mut |_| {}).unwrap(),
        );
    }
}
