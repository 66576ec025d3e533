//! `vcedit edit-image`: InfEdit on one image.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use edit::present::viz;
use edit::sampler::{
    edit_image, image_to_tensor, tensor_to_images, EditModel, EditPlan, SeededNoise,
};
use splat::Image;

use crate::args::editing::{ModelArgs, PromptArgs, SamplerArgs};
use crate::args::memory::MemoryCheckArg;
use crate::args::output::{output_file, probe_folder, require_extension, ForceArg};
use crate::args::ComputeArgs;
use crate::progress::Reporter;

/// Below this fraction of the image, the last step's blend region counts as empty (nothing could change).
const EMPTY_REGION_FRACTION: f64 = 0.005;

/// Edit one image from a source prompt to a target prompt (InfEdit: inversion-free, LCM, attention control).
#[derive(clap::Args, Debug)]
#[command(after_help = "Examples:
  vcedit edit-image --model ./LCM_Dreamshaper_v7 --image man.png \\
      --source \"a man\" --target \"a clown\" --out clown.png
  vcedit edit-image --model ./sd15 --taesd ./taesd --image cat.png \\
      --source \"a photo of a cat\" --target \"a photo of a dog\" \\
      --blend-words dog --save-attention attn/ --out dog.png
  vcedit edit-image --model demo --image vcedit-demo/before/view_000.png \\
      --source \"a red sphere\" --target \"a blue sphere\" --size 128 \\
      --cross 0.3 --thresh-e 0.3 --blend-level 1 --out blue.png

--model demo is the small model built into vcedit (128x128 images of the demo's procedural objects;
the settings its demo uses: --size 128 --cross 0.3 --thresh-e 0.3 --guidance-scale 3 --blend-level 1).")]
pub struct Args {
    #[command(flatten)]
    pub model: ModelArgs,
    /// Input image (PNG/JPEG; transparency is composited over white).
    #[arg(long, value_name = "FILE")]
    pub image: PathBuf,
    #[command(flatten)]
    pub prompts: PromptArgs,
    /// Output PNG.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    #[command(flatten)]
    pub force: ForceArg,
    /// Also write one attention heat map per target word and the local-blend mask into this folder.
    #[arg(long, value_name = "DIR")]
    pub save_attention: Option<PathBuf>,
    #[command(flatten)]
    pub compute: ComputeArgs,
    #[command(flatten)]
    pub sampler: SamplerArgs,
    #[command(flatten)]
    pub memory: MemoryCheckArg,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let settings = args.sampler.settings()?;
    let (w, h) = args.sampler.size();
    // Every argument is checked before any work, and both outputs before the first is written.
    require_extension(&args.out, "--out", &["png"], "the edited image")?;
    // The image first: `--image DIR --out DIR/o.png` is a folder given for an image, which the output
    // policy would otherwise report as an output inside an input folder.
    let input = Image::load(&args.image)?;
    // The model folders are inputs too: nothing is written inside them.
    let mut inputs = vec![args.image.as_path(), args.model.model.as_path()];
    inputs.extend(args.model.taesd.as_deref());
    output_file(&args.out, &inputs, args.force.force)?;
    if let Some(dir) = &args.save_attention {
        files::check_not_inputs(&[dir.as_path()], &inputs).context("--save-attention")?;
        probe_folder(dir).context("--save-attention")?;
    }

    let t0 = Instant::now();
    let model_dir = args.model.folder()?;
    let model = EditModel::load(&model_dir, args.model.taesd.as_deref())
        .with_context(|| format!("loading model {}", model_dir.display()))?
        .on(args.compute.open()?);
    let load_time = t0.elapsed();
    args.sampler.check_model(&model)?;
    args.prompts.check_words(&model.tokenizer, None)?;
    let (host, gpu) = edit::run::image_edit_memory(&model, (w, h));
    args.memory.check(host, "--size")?;
    args.memory
        .check_gpu(gpu, model.compute.gpu_free_bytes(), "--size")?;
    let input = input
        .over_background([1.0, 1.0, 1.0])
        .center_crop_to_aspect(w, h)
        .resize(w, h);
    let prompts = args.prompts.prompts();
    let plan = EditPlan::new(&model, &prompts, &settings, (w as usize, h as usize))?;

    let image = image_to_tensor(&input)?;
    let mut noise = SeededNoise::new(args.sampler.seed);
    let mut progress = Reporter::new().on_gpu(!model.compute.splat().is_cpu());
    progress.stage("editing steps", plan.timesteps.len() as u64);
    let t1 = Instant::now();
    let outcome = edit_image(&model, &plan, &image, &mut noise, &mut |_| {
        progress.advance(1)
    })?;
    progress.finish();
    let edit_time = t1.elapsed();

    let out = tensor_to_images(&outcome.image)?.remove(0);
    out.save_png(&args.out)?;
    // Against the source's own round trip through the codec (its latents decoded), so that the codec's
    // error is not taken for an edit.
    let source = tensor_to_images(&model.decode_unit(&outcome.state.x0)?)?.remove(0);
    let changed = edit::eval::metrics::changed_fraction(&[&source], &[&out], None)?;
    // The target-word region of the last step at image size, thresholded as the blend did.
    let (tau_e, _, _) = plan.thresholds.at(*plan.alpha.last().expect("steps"));
    let region: Option<Vec<f32>> = outcome
        .blend_maps
        .as_ref()
        .map(|bm| -> anyhow::Result<Vec<f32>> {
            let e = viz::resize_map(&bm.get(0)?, h as usize, w as usize)?;
            Ok(e.into_iter()
                .map(|v| f32::from(u8::from(v as f64 > tau_e)))
                .collect())
        })
        .transpose()?;
    let region_fraction = region
        .as_ref()
        .map(|m| m.iter().sum::<f32>() as f64 / m.len().max(1) as f64);
    match region_fraction {
        // How much the sampler's reconstruction of an unedited image drifts depends on the model
        // (1.4-3.4 % of the pixels with the first demo model, 14 % with the current one), so an edit
        // that could change nothing is named by its empty region, not by how little moved.
        Some(f) if f < EMPTY_REGION_FRACTION => eprintln!(
            "warning: the edit's blend region is empty ({:.1} % of the image): the target words' \
             attention stayed under the threshold {tau_e:.2}, so the result is the source's \
             reconstruction. Lower --thresh-e (a larger region), or choose --blend-words that name \
             what should change.",
            100.0 * f
        ),
        _ => super::edit::warn_if_unchanged(changed, "the image"),
    }

    if let Some(dir) = &args.save_attention {
        let maps = viz::word_maps(
            &outcome.state.controller.blend_store()?,
            plan.blend_size,
            &plan.target_tokens,
            (h as usize, w as usize),
        )?;
        for m in &maps {
            let path = dir.join(format!("attn_{}.png", viz::file_safe(&m.word)));
            viz::heat_image(&m.map, w, h).save_png(&path)?;
        }
        if let Some(mask) = &region {
            viz::mask_image(mask, w, h).save_png(&dir.join("mask.png"))?;
        }
        crate::out!(
            "attention maps: {} words and the blend mask in {}",
            maps.len(),
            dir.display()
        );
    }
    let steps = plan.timesteps.len();
    crate::out!(
        "wrote {} ({}x{}, {} steps, {:.2} s/step; model load {:.1} s)",
        args.out.display(),
        w,
        h,
        steps,
        edit_time.as_secs_f64() / steps as f64,
        load_time.as_secs_f64()
    );
    Ok(())
}
