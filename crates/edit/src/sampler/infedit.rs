//! InfEdit: inversion-free editing with an LCM, three latent branches and unified attention control.
//!
//! An [`EditPlan`] holds everything fixed during an edit (text conditioning, token alignment, timesteps);
//! a [`ViewState`] holds one view's per-step state (clean latents x0, the three branch latents, the last
//! predictions and the view's attention controller). The single-image sampler ([`edit_image`]) and VcEdit's
//! multi-view sampler both drive these two types, step by step, so the per-step state is always explicit.
//!
//! Equations (docs/algorithm.md §2.3, with ᾱ_t and ᾱ_prev of the current and next timestep):
//! ε_c = (z_S − √ᾱ_t x0)/√(1−ᾱ_t);  x̂0_B = x0 + [(z_B − z_S) − √(1−ᾱ_t)(ε_B − ε_S)]/√ᾱ_t;
//! σ² = η(1−ᾱ_prev);  dir = √(1−ᾱ_prev−σ²)(ε_B − ε_S + ε_c);
//! z_B ← √ᾱ_prev x̂0_B + dir + σ n;  z_S ← √ᾱ_prev x0 + dir + σ n   (the same n for every branch).

use candle_core::{Device, Tensor};
use diffusion::device::DeviceTensor;
use diffusion::scheduler::{LcmScheduler, LcmVariant};
use diffusion::unet::{AttentionHook, AttnCall, MapEdit, Qkv};

use super::align::{align_prompts, AlignError, AlignInputs, TokenAlignment};
use super::batch::{BatchLayout, Branch, SampleSettings};
use super::control::{
    mutual_at, progress_at, ControlSettings, EditController, RecordedMaps, DEFAULT_STORE_MAX_TOKENS,
};
use super::local_blend::{apply_local_blend, blend_maps, blend_masks, BlendThresholds};
use super::model::EditModel;
use super::noise::NoiseSource;

/// InfEdit's knobs; defaults are the reference app's (15 LCM steps, guidance 1/2, cross 0.7, self 0.3,
/// thresholds 0.6/0.6, η = 1, pure-noise start).
#[derive(Clone, Debug, serde::Serialize)]
pub struct InfEditSettings {
    pub steps: usize,
    /// LCM's original schedule length (timesteps are picked from it).
    pub original_steps: usize,
    #[serde(skip)]
    pub lcm_variant: LcmVariant,
    pub guidance_source: f64,
    pub guidance_target: f64,
    pub cross_replace: f64,
    pub self_replace: f64,
    pub thresh_e: f64,
    pub thresh_m: f64,
    pub eta: f64,
    /// `Some(strength)`: start from the source latents noised to the strength-truncated first timestep
    /// ("denoise" mode); `None`: start from pure noise (the reference default).
    pub denoise_strength: Option<f64>,
    /// The UNet level (0 = the latents' resolution, each down block halves it) whose cross-attention
    /// maps the local blend and CCM read. `None`: the coarsest down block with cross-attention, the
    /// reference's choice (SD 1.x: level 2, its "16×16 layers" at 512²). Which level localizes words is
    /// a property of the trained model, so a model unlike SD may need another.
    pub blend_level: Option<usize>,
}

impl Default for InfEditSettings {
    fn default() -> Self {
        Self {
            steps: 15,
            original_steps: 50,
            lcm_variant: LcmVariant::Diffusers022,
            guidance_source: 1.0,
            guidance_target: 2.0,
            cross_replace: 0.7,
            self_replace: 0.3,
            thresh_e: 0.6,
            thresh_m: 0.6,
            eta: 1.0,
            denoise_strength: None,
            blend_level: None,
        }
    }
}

impl InfEditSettings {
    /// Steps skipped at the start: those strength truncation leaves out in denoise mode.
    pub fn start_steps(&self) -> Result<usize, EditError> {
        let Some(s) = self.denoise_strength else {
            return Ok(0);
        };
        if !(s > 0.0 && s <= 1.0) {
            return Err(EditError::Settings(format!(
                "strength {s} must be in (0, 1]"
            )));
        }
        let init = ((self.steps as f64 * s) as usize).min(self.steps);
        if init == 0 {
            return Err(EditError::Settings(format!(
                "strength {s} × {} steps leaves no step to run",
                self.steps
            )));
        }
        Ok(self.steps - init)
    }

    /// UNet samples one view computes at executed step `i`: in its real pass, or in CCM's recording
    /// pass before it (see [`BatchLayout::needed`]).
    pub fn unet_samples(&self, i: usize, recording: bool) -> Result<usize, EditError> {
        let progress = progress_at(i, self.start_steps()?, self.steps);
        let settings = SampleSettings {
            cfg: self.guidance_target > 1.0,
            guidance_source: self.guidance_source,
            skip_unread: true,
        };
        Ok(BatchLayout::needed(&settings, mutual_at(progress, self.self_replace), recording).len())
    }
}

/// The prompts of an edit.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct EditPrompts {
    pub source: String,
    pub target: String,
    /// Target-blend ("local") words: the region the edit may change. VcEdit uses the whole target prompt.
    pub target_blend: String,
    /// Source-blend ("mutual") words: regions kept from the source. Must appear in both prompts.
    pub source_blend: String,
    /// Unconditional text of the source and layout branches.
    pub positive: String,
    /// Unconditional text of the target branch.
    pub negative: String,
}

impl EditPrompts {
    /// Source → target with the whole target prompt as blend words (VcEdit's choice).
    pub fn new(source: &str, target: &str) -> Self {
        Self {
            source: source.into(),
            target: target.into(),
            target_blend: target.into(),
            ..Default::default()
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum EditError {
    #[error("{which} prompt: {source}")]
    Prompt {
        which: &'static str,
        source: diffusion::tokenizer::TokenizerError,
    },
    #[error(transparent)]
    Align(#[from] AlignError),
    #[error("{0}")]
    Scheduler(#[from] diffusion::scheduler::SchedulerError),
    #[error("{0}")]
    Settings(String),
    #[error("{0}")]
    Candle(#[from] candle_core::Error),
}

/// Everything fixed during an edit.
pub struct EditPlan {
    pub settings: InfEditSettings,
    pub prompts: EditPrompts,
    /// Text conditioning in batch order [S_u, T_u, M_u, S_c, T_c, M_c] (CFG) or [S, T, M].
    pub embeddings: Tensor,
    pub cfg: bool,
    pub alignment: TokenAlignment,
    /// Executed timesteps (after strength truncation).
    pub timesteps: Vec<usize>,
    /// ᾱ of each executed timestep, and of the one after it (the last repeats its own, as the reference).
    pub alpha: Vec<f64>,
    pub alpha_prev: Vec<f64>,
    /// Steps skipped by strength truncation; the schedule's full length.
    pub start_steps: usize,
    pub num_steps: usize,
    pub latent_size: (usize, usize),
    pub latent_channels: usize,
    /// Spatial size of the cross-attention layers used by the local blend.
    pub blend_size: (usize, usize),
    /// Target prompt tokens (SOT .. EOT) as raw BPE pieces, for per-word attention maps.
    pub target_tokens: Vec<String>,
    /// Real tokens (with SOT/EOT) of the source prompt.
    pub source_len: usize,
    pub thresholds: BlendThresholds,
    /// Leave out the UNet work nobody reads: the samples [`BatchLayout`] drops, and the blocks of a CCM
    /// recording pass after its last recorded layer. `false` does all of it, as the reference does: the
    /// same results to float rounding, more work (for tests and comparisons).
    pub skip_unread: bool,
}

/// Spatial size of the down/up cross-attention layers at UNet level `level`, or with `None` at the
/// coarsest level that has them (SD 1.x: latent/4, the reference's "16×16 layers" at 512²). A level
/// without cross-attention is an error naming the levels that have it.
pub fn blend_layer_size(
    down_block_types: &[String],
    latent: (usize, usize),
    level: Option<usize>,
) -> Result<(usize, usize), EditError> {
    let (mut h, mut w) = latent;
    let mut sizes = Vec::new();
    for (i, kind) in down_block_types.iter().enumerate() {
        if kind.contains("CrossAttn") {
            sizes.push((i, (h, w)));
        }
        if i + 1 < down_block_types.len() {
            // A stride-2 conv with padding 1: ceil(n / 2).
            h = h.div_ceil(2);
            w = w.div_ceil(2);
        }
    }
    match level {
        None => Ok(sizes.last().map_or(latent, |&(_, size)| size)),
        Some(l) => {
            sizes
                .iter()
                .find(|&&(i, _)| i == l)
                .map(|&(_, size)| size)
                .ok_or_else(|| {
                    let with: Vec<String> = sizes.iter().map(|(i, _)| i.to_string()).collect();
                    EditError::Settings(format!(
                    "blend level {l}: the UNet has no cross-attention there (levels with it: {})",
                    if with.is_empty() { "none".to_string() } else { with.join(", ") }
                ))
                })
        }
    }
}

impl EditPlan {
    /// Whether `model` can edit images of `image_size` (width, height) pixels: a cheap check, made before
    /// any work by callers that validate their arguments up front (and again by [`EditPlan::new`]).
    pub fn check_size(model: &EditModel, image_size: (usize, usize)) -> Result<(), EditError> {
        let f = model.downscale();
        let (iw, ih) = image_size;
        if iw % f != 0 || ih % f != 0 || iw == 0 || ih == 0 {
            return Err(EditError::Settings(format!(
                "image size {iw}x{ih} must be a positive multiple of {f} (the codec's downscale)"
            )));
        }
        // Each down block but the last halves the latents; odd sizes would not line up with the up path.
        let levels = model.unet.config().down_block_types.len().saturating_sub(1) as u32;
        let multiple = f * 2usize.pow(levels);
        if iw % multiple != 0 || ih % multiple != 0 {
            return Err(EditError::Settings(format!(
                "image size {iw}x{ih} must be a multiple of {multiple} for this model \
                 ({f}x codec, {levels} UNet downsamplings)"
            )));
        }
        Ok(())
    }

    /// Whether `model` has cross-attention at the chosen blend level (see
    /// [`InfEditSettings::blend_level`]): the cheap check callers make before any work.
    pub fn check_blend_level(model: &EditModel, level: Option<usize>) -> Result<(), EditError> {
        let blocks = &model.unet.config().down_block_types;
        // Which levels have cross-attention does not depend on the latents' size.
        blend_layer_size(blocks, (1, 1), level).map(|_| ())
    }

    /// Prepares an edit of images of `image_size` (width, height) pixels.
    pub fn new(
        model: &EditModel,
        prompts: &EditPrompts,
        settings: &InfEditSettings,
        image_size: (usize, usize),
    ) -> Result<Self, EditError> {
        Self::check_size(model, image_size)?;
        let f = model.downscale();
        let (iw, ih) = image_size;
        let latent_size = (ih / f, iw / f);
        let tok = &model.tokenizer;
        let strict = |which: &'static str, text: &str| {
            tok.encode_strict(text)
                .map_err(|source| EditError::Prompt { which, source })
        };
        let enc_source = strict("source", &prompts.source)?;
        let enc_target = strict("target", &prompts.target)?;
        let enc_pos = strict("positive", &prompts.positive)?;
        let enc_neg = strict("negative", &prompts.negative)?;
        strict("target blend words", &prompts.target_blend)?;
        strict("source blend words", &prompts.source_blend)?;

        let device = Device::Cpu;
        let ids =
            diffusion::clip::ids_tensor(&[enc_pos, enc_neg, enc_source, enc_target], &device)?;
        let hidden = model.encode_text(&ids)?;
        let (pos, neg, src, tgt) = (
            hidden.get(0)?,
            hidden.get(1)?,
            hidden.get(2)?,
            hidden.get(3)?,
        );
        // As `InfEditSettings::unet_samples` decides.
        let cfg = settings.guidance_target > 1.0;
        let embeddings = if cfg {
            Tensor::stack(&[&pos, &neg, &pos, &src, &tgt, &src], 0)?
        } else {
            Tensor::stack(&[&src, &tgt, &src], 0)?
        };

        let rows = |t: &Tensor| -> candle_core::Result<Vec<Vec<f32>>> { t.to_vec2::<f32>() };
        let source_ids = tok.encode_unpadded(&prompts.source);
        let target_ids = tok.encode_unpadded(&prompts.target);
        let alignment = align_prompts(&AlignInputs {
            source_ids: &source_ids,
            target_ids: &target_ids,
            local_ids: &tok.encode_unpadded(&prompts.target_blend),
            mutual_ids: &tok.encode_unpadded(&prompts.source_blend),
            source_hidden: &rows(&src)?,
            target_hidden: &rows(&tgt)?,
            max_len: model.text_encoder.max_positions(),
        })?;

        let mut sched = LcmScheduler::new(model.scheduler_config.clone(), settings.lcm_variant)?;
        let full: Vec<usize> = sched
            .set_timesteps(settings.steps, Some(settings.original_steps), 1.0)?
            .to_vec();
        let start_steps = settings.start_steps()?;
        let timesteps = full[start_steps..].to_vec();
        let sched_alpha = |t: usize| sched.alpha_cumprod(t);
        let mut alpha = Vec::new();
        let mut alpha_prev = Vec::new();
        for (i, &t) in timesteps.iter().enumerate() {
            alpha.push(sched_alpha(t)?);
            alpha_prev.push(sched_alpha(*timesteps.get(i + 1).unwrap_or(&t))?);
        }

        let blend_size = blend_layer_size(
            &model.unet.config().down_block_types,
            latent_size,
            settings.blend_level,
        )?;
        // Raw BPE pieces (with their `</w>` word ends) so per-word maps can group sub-word tokens.
        let target_tokens = target_ids
            .iter()
            .map(|&id| tok.id_to_token(id).unwrap_or("").to_string())
            .collect();
        Ok(Self {
            settings: settings.clone(),
            prompts: prompts.clone(),
            embeddings,
            cfg,
            alignment,
            timesteps,
            alpha,
            alpha_prev,
            start_steps,
            num_steps: settings.steps,
            latent_size,
            latent_channels: model.latent_channels(),
            blend_size,
            target_tokens,
            source_len: source_ids.len(),
            thresholds: BlendThresholds {
                thresh_e: settings.thresh_e,
                thresh_m: settings.thresh_m,
                temperature: 0.15,
                dynamic_me: false,
            },
            skip_unread: true,
        })
    }

    /// A fresh attention controller for one view.
    pub fn controller(&self) -> EditController {
        EditController::new(
            ControlSettings {
                num_steps: self.num_steps,
                start_steps: self.start_steps,
                cross_replace: self.settings.cross_replace,
                self_replace: self.settings.self_replace,
                blend_size: self.blend_size,
                store_max_tokens: DEFAULT_STORE_MAX_TOKENS,
                samples: SampleSettings {
                    cfg: self.cfg,
                    guidance_source: self.settings.guidance_source,
                    skip_unread: self.skip_unread,
                },
            },
            &self.alignment,
        )
    }

    /// Shape of one view's latents.
    pub fn latent_shape(&self) -> [usize; 4] {
        [
            1,
            self.latent_channels,
            self.latent_size.0,
            self.latent_size.1,
        ]
    }

    /// Initial state of a view from its clean latents and the initial noise (shared by all views).
    pub fn initial_state(&self, x0: Tensor, init_noise: &Tensor) -> candle_core::Result<ViewState> {
        let z = match self.settings.denoise_strength {
            None => init_noise.clone(),
            Some(_) => {
                let a = self.alpha[0];
                x0.affine(a.sqrt(), 0.0)?
                    .add(&init_noise.affine((1.0 - a).sqrt(), 0.0)?)?
            }
        };
        Ok(ViewState {
            x0,
            z_s: z.clone(),
            z_t: z.clone(),
            z_m: z,
            pred_t: None,
            pred_m: None,
            offset_t: None,
            offset_m: None,
            controller: self.controller(),
        })
    }

    /// One UNet pass of a view at step `i` with the view's controller as hook; returns the guided noise
    /// predictions (ε_S, ε_T, ε_M). Does not advance the controller's step.
    pub fn predict(
        &self,
        model: &EditModel,
        view: &mut ViewState,
        i: usize,
    ) -> candle_core::Result<[Tensor; 3]> {
        let mut out = self.predict_views(model, &mut [view], i)?;
        Ok(out.remove(0))
    }

    /// One UNet pass for several views at step `i`: their branch batches stacked into one call (a GPU
    /// keeps busy where one view's batch would leave it idle), each view's controller hooked to
    /// its own slice of the batch. Per view, the same result as [`Self::predict`]. A view's batch holds
    /// the samples its controller's [`EditController::layout`] names: the same for views at one step.
    pub fn predict_views(
        &self,
        model: &EditModel,
        views: &mut [&mut ViewState],
        i: usize,
    ) -> candle_core::Result<Vec<[Tensor; 3]>> {
        let (layout, input, context, t) = self.batch_inputs(views, i)?;
        let mut hook = ViewBatch(views.iter_mut().map(|view| &mut view.controller).collect());
        // The reference does not pass LCM's guidance embedding (timestep_cond); classic CFG is done here.
        let out = model.predict(&input, &t, &context, Some(&mut hook))?;
        let per = layout.len();
        (0..views.len())
            .map(|v| self.guide(&layout, &out.narrow(0, v * per, per)?))
            .collect()
    }

    /// CCM's recording pass of several views at step `i` (before the step's real pass): the small
    /// layers' conditional maps per view (see [`EditController::start_recording`]), and the UNet
    /// samples per view it took. Changes no state; the pass ends after the last recorded layer unless
    /// [`Self::skip_unread`] is off.
    pub fn record_views(
        &self,
        model: &EditModel,
        views: &mut [&mut ViewState],
        i: usize,
    ) -> candle_core::Result<(Vec<Vec<RecordedMaps>>, usize)> {
        for view in views.iter_mut() {
            view.controller.start_recording();
        }
        let (layout, input, context, t) = self.batch_inputs(views, i)?;
        let mut hook = ViewBatch(views.iter_mut().map(|view| &mut view.controller).collect());
        model.observe(&input, &t, &context, &mut hook)?;
        let maps = views
            .iter_mut()
            .map(|view| view.controller.finish_recording())
            .collect();
        Ok((maps, layout.len()))
    }

    /// The batch of one UNet call for `views` at step `i`: its per-view layout (the samples the views'
    /// controllers name, the same for views at one step), the latents, the text conditioning and the
    /// timestep.
    fn batch_inputs(
        &self,
        views: &[&mut ViewState],
        i: usize,
    ) -> candle_core::Result<(BatchLayout, Tensor, Tensor, Tensor)> {
        let layout = views
            .first()
            .map(|v| v.controller.layout())
            .ok_or_else(|| candle_core::Error::Msg("no view to predict".into()))?;
        if views.iter().any(|v| v.controller.layout() != layout) {
            candle_core::bail!("views batched into one UNet call are at different steps");
        }
        let mut inputs = Vec::with_capacity(views.len() * layout.len());
        for view in views.iter() {
            inputs.extend(layout.samples().iter().map(|s| match s.branch {
                Branch::Source => &view.z_s,
                Branch::Target => &view.z_t,
                Branch::Layout => &view.z_m,
            }));
        }
        let input = Tensor::cat(&inputs, 0)?;
        let positions = layout.full_positions(self.cfg);
        let one_view = if positions.len() == self.embeddings.dim(0)? {
            self.embeddings.clone()
        } else {
            let idx = Tensor::new(positions.as_slice(), &Device::Cpu)?;
            self.embeddings.index_select(&idx, 0)?
        };
        let context = if views.len() == 1 {
            one_view
        } else {
            Tensor::cat(&vec![&one_view; views.len()], 0)?
        };
        let t = Tensor::new(&[self.timesteps[i] as f32], &Device::Cpu)?;
        Ok((layout, input, context, t))
    }

    /// (ε_S, ε_T, ε_M) of one view from its slice of the UNet output, laid out as `layout`. A branch
    /// whose unconditional sample was not computed has guidance weight 1 (see [`BatchLayout::needed`]):
    /// its ε is the conditional prediction.
    fn guide(&self, layout: &BatchLayout, out: &Tensor) -> candle_core::Result<[Tensor; 3]> {
        let part = |p: usize| -> candle_core::Result<Tensor> { out.narrow(0, p, 1) };
        let guide = |b: Branch, g: f64| -> candle_core::Result<Tensor> {
            let c = part(
                layout
                    .position(true, b)
                    .expect("conditional samples always run"),
            )?;
            match layout.position(false, b) {
                Some(u) => {
                    let u = part(u)?;
                    u.add(&(c - &u)?.affine(g, 0.0)?)
                }
                None => Ok(c),
            }
        };
        let gs = self.settings.guidance_source;
        let gt = self.settings.guidance_target;
        Ok([
            guide(Branch::Source, gs)?,
            guide(Branch::Target, gt)?,
            guide(Branch::Layout, gs)?,
        ])
    }

    /// The DDCM (virtual inversion) step for one branch B against the source: returns (z_S', z_B', x̂0_B,
    /// offset) where z_B' = √ᾱ_prev x̂0_B + offset (the offset is `dir + σ n`, or `None` for a one-step
    /// schedule where z_B' = x̂0_B).
    pub fn ddcm(
        &self,
        i: usize,
        z_s: &Tensor,
        z_b: &Tensor,
        eps_s: &Tensor,
        eps_b: &Tensor,
        x0: &Tensor,
        noise: &Tensor,
    ) -> candle_core::Result<(Tensor, Tensor, Tensor, Option<Tensor>)> {
        let (a_t, a_prev) = (self.alpha[i], self.alpha_prev[i]);
        let (b_t, b_prev) = (1.0 - a_t, 1.0 - a_prev);
        let var = self.settings.eta * b_prev;
        let diff = (eps_b - eps_s)?;
        let pred = x0
            .add(&((z_b - z_s)? - diff.affine(b_t.sqrt(), 0.0)?)?.affine(1.0 / a_t.sqrt(), 0.0)?)?;
        if self.num_steps <= 1 {
            return Ok((x0.clone(), pred.clone(), pred, None));
        }
        let dir_noise = self.dir_and_noise(i, z_s, &diff, x0, noise, var)?;
        let z_b_next = pred.affine(a_prev.sqrt(), 0.0)?.add(&dir_noise)?;
        let z_s_next = x0.affine(a_prev.sqrt(), 0.0)?.add(&dir_noise)?;
        Ok((z_s_next, z_b_next, pred, Some(dir_noise)))
    }

    /// `dir + σ n` of the DDCM step (shared by both branches' updates).
    fn dir_and_noise(
        &self,
        i: usize,
        z_s: &Tensor,
        eps_diff: &Tensor,
        x0: &Tensor,
        noise: &Tensor,
        var: f64,
    ) -> candle_core::Result<Tensor> {
        let (a_t, a_prev) = (self.alpha[i], self.alpha_prev[i]);
        let eps_c = (z_s - x0.affine(a_t.sqrt(), 0.0)?)?.affine(1.0 / (1.0 - a_t).sqrt(), 0.0)?;
        let dir_scale = ((1.0 - a_prev) - var).max(0.0).sqrt();
        let dir = (eps_diff + eps_c)?.affine(dir_scale, 0.0)?;
        dir.add(&noise.affine(var.sqrt(), 0.0)?)
    }

    /// Runs the DDCM update of step `i` for a view from its guided predictions, without blending: both
    /// branch pairs (S,T) and (S,M) with the same noise; z_S comes from the (S,M) pair as in the reference.
    pub fn update(
        &self,
        view: &mut ViewState,
        i: usize,
        eps: &[Tensor; 3],
        noise: &Tensor,
    ) -> candle_core::Result<()> {
        let (_, zt, pt, ot) =
            self.ddcm(i, &view.z_s, &view.z_t, &eps[0], &eps[1], &view.x0, noise)?;
        let (zs, zm, pm, om) =
            self.ddcm(i, &view.z_s, &view.z_m, &eps[0], &eps[2], &view.x0, noise)?;
        view.z_s = zs;
        view.z_t = zt;
        view.z_m = zm;
        view.pred_t = Some(pt);
        view.pred_m = Some(pm);
        view.offset_t = ot;
        view.offset_m = om;
        Ok(())
    }

    /// Replaces the step's predictions x̂0_T, x̂0_M (VcEdit's ECM) and recomputes the branch latents from
    /// them with the step's own direction and noise terms.
    pub fn rebase(
        &self,
        view: &mut ViewState,
        i: usize,
        pred_t: Tensor,
        pred_m: Tensor,
    ) -> candle_core::Result<()> {
        let a_prev = self.alpha_prev[i].sqrt();
        let next = |pred: &Tensor, offset: &Option<Tensor>| -> candle_core::Result<Tensor> {
            match offset {
                Some(o) => pred.affine(a_prev, 0.0)?.add(o),
                None => Ok(pred.clone()),
            }
        };
        view.z_t = next(&pred_t, &view.offset_t)?;
        view.z_m = next(&pred_m, &view.offset_m)?;
        view.pred_t = Some(pred_t);
        view.pred_m = Some(pred_m);
        Ok(())
    }

    /// Whether the local blend of step `i` (called after the controller's `end_step`) takes the layout
    /// branch in the `me` region: the reference's second-to-last step.
    pub fn use_layout_branch(&self, view: &ViewState) -> bool {
        view.controller.cur_step() + self.start_steps + 1 == self.num_steps
    }

    /// Step `i` of one view's edit, in the reference's order: the UNet's predictions, the controller's
    /// step end, the update with the next noise tensor, and from the second step on the local blend (whose
    /// maps it returns).
    pub fn step(
        &self,
        model: &EditModel,
        view: &mut ViewState,
        i: usize,
        noise: &mut dyn NoiseSource,
    ) -> candle_core::Result<Option<Tensor>> {
        let eps = self.predict(model, view, i)?;
        view.controller.end_step();
        let n = noise.sample(&self.latent_shape())?;
        self.update(view, i, &eps, &n)?;
        if i > 0 {
            Ok(Some(self.local_blend(view, i)?))
        } else {
            Ok(None)
        }
    }

    /// The local blend of step `i` from the view's own attention store (InfEdit's single-image path).
    pub fn local_blend(&self, view: &mut ViewState, i: usize) -> candle_core::Result<Tensor> {
        let maps = blend_maps(
            &view.controller.blend_store()?,
            self.blend_size,
            &self.alignment,
            self.latent_size,
            0.0,
        )?;
        self.blend_with_maps(view, i, &maps)?;
        Ok(maps)
    }

    /// Applies the local blend with given maps `[3, H, W]` (VcEdit passes 3D-consistent maps).
    pub fn blend_with_maps(
        &self,
        view: &mut ViewState,
        i: usize,
        maps: &Tensor,
    ) -> candle_core::Result<()> {
        let masks = blend_masks(maps, self.thresholds.at(self.alpha[i]))?;
        let has_e = self.alignment.alpha_e.iter().any(|&a| a > 0.0);
        view.z_t = apply_local_blend(
            &view.z_s,
            &view.z_t,
            &view.z_m,
            &masks,
            has_e,
            self.use_layout_branch(view),
        )?;
        Ok(())
    }
}

/// The controllers of the views batched into one UNet call, each given its own equal slice of every
/// attention call's batch. With one view the controller sees the call unchanged.
struct ViewBatch<'a>(Vec<&'a mut EditController>);

impl ViewBatch<'_> {
    /// Splits `tensors` (same batch) into per-view slices, lets `f` rewrite each view's slices, and
    /// concatenates the results back in view order.
    fn per_view<const N: usize>(
        &mut self,
        call: &AttnCall,
        tensors: [DeviceTensor; N],
        mut f: impl FnMut(
            &mut EditController,
            &AttnCall,
            [DeviceTensor; N],
        ) -> candle_core::Result<[DeviceTensor; N]>,
    ) -> candle_core::Result<[DeviceTensor; N]> {
        let views = self.0.len();
        if views == 1 {
            return f(self.0[0], call, tensors);
        }
        if !call.batch.is_multiple_of(views) {
            candle_core::bail!(
                "{}: batch {} does not split into {views} views",
                call.layer,
                call.batch
            );
        }
        let per = call.batch / views;
        let slice_call = AttnCall {
            batch: per,
            ..*call
        };
        let mut parts: Vec<Vec<DeviceTensor>> = vec![Vec::with_capacity(views); N];
        for (v, controller) in self.0.iter_mut().enumerate() {
            let slices = tensors
                .iter()
                .map(|t| t.narrow(0, v * per, per))
                .collect::<candle_core::Result<Vec<_>>>()?;
            let slices: [DeviceTensor; N] = slices.try_into().expect("N slices");
            for (k, t) in f(controller, &slice_call, slices)?.into_iter().enumerate() {
                parts[k].push(t);
            }
        }
        let joined = parts
            .iter()
            .map(|p| DeviceTensor::cat(&p.iter().collect::<Vec<_>>(), 0))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(joined.try_into().expect("N joined"))
    }
}

impl AttentionHook for ViewBatch<'_> {
    fn qkv(&mut self, call: &AttnCall, qkv: Qkv) -> candle_core::Result<Qkv> {
        let [q, k, v] = self.per_view(call, [qkv.q, qkv.k, qkv.v], |c, call, [q, k, v]| {
            let Qkv { q, k, v } = c.qkv(call, Qkv { q, k, v })?;
            Ok([q, k, v])
        })?;
        Ok(Qkv { q, k, v })
    }

    fn wants_probs(&self, call: &AttnCall) -> bool {
        // Each controller judges the call as it will see it: its own slice of the batch.
        let views = self.0.len();
        let slice_call = AttnCall {
            batch: call.batch / views,
            ..*call
        };
        self.0.iter().any(|c| c.wants_probs(&slice_call))
    }

    fn probs(&mut self, call: &AttnCall, probs: DeviceTensor) -> candle_core::Result<DeviceTensor> {
        let [probs] = self.per_view(call, [probs], |c, call, [p]| Ok([c.probs(call, p)?]))?;
        Ok(probs)
    }

    fn map_edits(&self, call: &AttnCall) -> Vec<MapEdit> {
        // Each controller's edits of its own slice, moved to the slice's rows of the whole batch.
        let per = call.batch / self.0.len();
        let slice_call = AttnCall {
            batch: per,
            ..*call
        };
        let mut edits = Vec::new();
        for (v, c) in self.0.iter().enumerate() {
            edits.extend(c.map_edits(&slice_call).into_iter().map(|e| MapEdit {
                row: e.row + v * per,
                source: e.source + v * per,
                ..e
            }));
        }
        edits
    }

    fn finished(&self) -> bool {
        self.0.iter().all(|c| c.finished())
    }
}

/// One view's per-step state.
pub struct ViewState {
    /// Clean latents of the source image.
    pub x0: Tensor,
    pub z_s: Tensor,
    pub z_t: Tensor,
    pub z_m: Tensor,
    /// Last x̂0 of the target and layout branches.
    pub pred_t: Option<Tensor>,
    pub pred_m: Option<Tensor>,
    /// The last step's `dir + σ n` of each branch (z = √ᾱ_prev x̂0 + offset).
    pub offset_t: Option<Tensor>,
    pub offset_m: Option<Tensor>,
    pub controller: EditController,
}

/// Result of a single-image edit.
pub struct EditOutcome {
    /// Edited image `[1, 3, H, W]` in [0, 1].
    pub image: Tensor,
    /// The final state (controller with its attention store, last predictions).
    pub state: ViewState,
    /// The last local-blend maps `[3, H, W]` (e, m, me), if a blend ran.
    pub blend_maps: Option<Tensor>,
}

/// Edits one image `[1, 3, H, W]` in [-1, 1]. Noise is drawn in the reference's order: the codec's posterior
/// sample (VAE only), the initial latents, then one tensor per step. `on_step(i)` is called after each step.
pub fn edit_image(
    model: &EditModel,
    plan: &EditPlan,
    image: &Tensor,
    noise: &mut dyn NoiseSource,
    on_step: &mut dyn FnMut(usize),
) -> candle_core::Result<EditOutcome> {
    let x0 = model.encode(image, noise)?;
    let init = noise.sample(&plan.latent_shape())?;
    let mut view = plan.initial_state(x0, &init)?;
    let mut last_maps = None;
    for i in 0..plan.timesteps.len() {
        if let Some(maps) = plan.step(model, &mut view, i, noise)? {
            last_maps = Some(maps);
        }
        on_step(i);
    }
    let pred = view.pred_t.clone().expect("at least one step ran");
    let image = model.decode_unit(&pred)?;
    Ok(EditOutcome {
        image,
        state: view,
        blend_maps: last_maps,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blend_layers_are_the_coarsest_cross_attention_resolution() {
        let sd = [
            "CrossAttnDownBlock2D",
            "CrossAttnDownBlock2D",
            "CrossAttnDownBlock2D",
            "DownBlock2D",
        ]
        .map(String::from);
        let size =
            |blocks: &[String], latent, level| blend_layer_size(blocks, latent, level).unwrap();
        assert_eq!(size(&sd, (64, 64), None), (16, 16));
        assert_eq!(size(&sd, (32, 48), None), (8, 12));
        let tiny = [
            "CrossAttnDownBlock2D",
            "CrossAttnDownBlock2D",
            "DownBlock2D",
        ]
        .map(String::from);
        assert_eq!(size(&tiny, (16, 16), None), (8, 8));
        assert_eq!(size(&sd, (9, 9), None), (3, 3));
    }

    #[test]
    fn the_default_edit_computes_70_unet_samples_per_view_where_the_reference_computes_102() {
        let s = InfEditSettings::default();
        let real: Vec<usize> = (0..15).map(|i| s.unet_samples(i, false).unwrap()).collect();
        // Progress (i + 1) / 15 below self_replace 0.3 for i < 4: S_u still lends T_u its Q/K.
        assert_eq!(real[..4], [5; 4]);
        assert_eq!(real[4..], [4; 11]);
        // CCM's default steps (6 and 13) record with the conditional half only.
        let recording: usize = [6, 13]
            .iter()
            .map(|&i| s.unet_samples(i, true).unwrap())
            .sum();
        assert_eq!(real.iter().sum::<usize>() + recording, 70);
        let source_guided = InfEditSettings {
            guidance_source: 1.5,
            ..InfEditSettings::default()
        };
        assert_eq!(source_guided.unet_samples(10, false).unwrap(), 6);
        let denoise = InfEditSettings {
            denoise_strength: Some(0.5),
            ..InfEditSettings::default()
        };
        // 8 steps skipped: executed step 0 is at progress 9/15, mutual.
        assert_eq!(denoise.start_steps().unwrap(), 8);
        assert_eq!(denoise.unet_samples(0, false).unwrap(), 4);
    }

    #[test]
    fn a_chosen_blend_level_must_have_cross_attention() {
        // The demo model's layout: no attention at full latent resolution.
        let demo = [
            "DownBlock2D",
            "CrossAttnDownBlock2D",
            "CrossAttnDownBlock2D",
            "DownBlock2D",
        ]
        .map(String::from);
        assert_eq!(blend_layer_size(&demo, (32, 32), None).unwrap(), (8, 8));
        assert_eq!(
            blend_layer_size(&demo, (32, 32), Some(1)).unwrap(),
            (16, 16)
        );
        assert_eq!(blend_layer_size(&demo, (32, 32), Some(2)).unwrap(), (8, 8));
        for level in [0, 3, 7] {
            let err = blend_layer_size(&demo, (32, 32), Some(level))
                .unwrap_err()
                .to_string();
            assert!(err.contains(&format!("blend level {level}")), "{err}");
            assert!(err.contains("levels with it: 1, 2"), "{err}");
        }
    }
}
