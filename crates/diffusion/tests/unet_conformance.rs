//! UNet conformance against diffusers (fixtures from tools/make_unet_fixtures.py) and the hook interface.

use std::collections::{HashMap, HashSet};

use candle_core::{Result, Tensor};
use diffusion::device::DeviceTensor;
use diffusion::unet::{AttentionHook, AttnCall, AttnKind, Qkv, UNet2DConditionModel};
use testkit::paths::{load_tensors, repo};

mod common;
use common::{in_bf16, max_abs_diff, relative_l2};

fn load_model(name: &str) -> UNet2DConditionModel {
    let dir = repo().join("fixtures/models").join(name).join("unet");
    UNet2DConditionModel::from_files(
        &dir.join("config.json"),
        &[dir.join("diffusion_pytorch_model.safetensors")],
    )
    .unwrap_or_else(|e| panic!("{name}: {e}"))
}

fn load_fixture(name: &str) -> HashMap<String, Tensor> {
    load_tensors(&repo().join(format!("fixtures/unet/{name}.safetensors")))
}

fn run(
    model: &UNet2DConditionModel,
    fx: &HashMap<String, Tensor>,
    hook: Option<&mut dyn AttentionHook>,
) -> Tensor {
    model
        .forward(
            &fx["sample"],
            &fx["timesteps"],
            &fx["encoder_hidden_states"],
            fx.get("timestep_cond"),
            hook,
        )
        .unwrap()
}

fn layers_with_prefix(fx: &HashMap<String, Tensor>, prefix: &str) -> Vec<String> {
    let mut names: Vec<String> = fx
        .keys()
        .filter_map(|k| k.strip_prefix(prefix).map(String::from))
        .collect();
    names.sort();
    names
}

/// Records the probabilities of the named layers (and only asks for those).
struct Capture {
    wanted: HashSet<String>,
    seen: HashMap<String, (AttnKind, Tensor)>,
    calls: Vec<(String, AttnKind, usize, usize)>,
}

impl AttentionHook for Capture {
    fn qkv(&mut self, call: &AttnCall, qkv: Qkv) -> Result<Qkv> {
        self.calls
            .push((call.layer.to_string(), call.kind, call.height, call.width));
        assert_eq!(qkv.q.dims()[0], call.batch);
        assert_eq!(qkv.q.dims()[1], call.heads);
        assert_eq!(qkv.q.dims()[2], call.height * call.width);
        Ok(qkv)
    }
    fn wants_probs(&self, call: &AttnCall) -> bool {
        self.wanted.contains(call.layer)
    }
    fn probs(&mut self, call: &AttnCall, probs: DeviceTensor) -> Result<DeviceTensor> {
        self.seen
            .insert(call.layer.to_string(), (call.kind, probs.to_cpu()?));
        Ok(probs)
    }
}

/// Replaces the probabilities of batch items 1.. with given maps in the named layers.
struct ReplaceMaps(HashMap<String, Tensor>);

impl AttentionHook for ReplaceMaps {
    fn wants_probs(&self, call: &AttnCall) -> bool {
        self.0.contains_key(call.layer)
    }
    fn probs(&mut self, call: &AttnCall, probs: DeviceTensor) -> Result<DeviceTensor> {
        let maps = &self.0[call.layer];
        let rest = probs.same_device(&maps.narrow(0, 1, call.batch - 1)?)?;
        DeviceTensor::cat(&[&probs.narrow(0, 0, 1)?, &rest], 0)
    }
}

/// In self-attention, the last batch item attends with item 0's keys and values.
struct SwapLastKv;

impl AttentionHook for SwapLastKv {
    fn qkv(&mut self, call: &AttnCall, qkv: Qkv) -> Result<Qkv> {
        if call.kind != AttnKind::SelfAttn {
            return Ok(qkv);
        }
        let swap = |t: &DeviceTensor| -> Result<DeviceTensor> {
            DeviceTensor::cat(&[&t.narrow(0, 0, call.batch - 1)?, &t.narrow(0, 0, 1)?], 0)
        };
        Ok(Qkv {
            k: swap(&qkv.k)?,
            v: swap(&qkv.v)?,
            ..qkv
        })
    }
    fn wants_probs(&self, _call: &AttnCall) -> bool {
        false
    }
}

fn check_model(name: &str) {
    let model = load_model(name);
    let fx = load_fixture(name);
    let plain = run(&model, &fx, None);
    let err = max_abs_diff(&plain, &fx["noise_pred"]);
    println!("{name}: noise_pred max abs error {err:e}");
    assert!(
        err <= 1e-4,
        "{name}: noise prediction differs from diffusers by {err}"
    );

    // A pass-through hook that captures maps must not change the output.
    let wanted: HashSet<String> = layers_with_prefix(&fx, "probs.").into_iter().collect();
    let mut capture = Capture {
        wanted: wanted.clone(),
        seen: HashMap::new(),
        calls: Vec::new(),
    };
    let hooked = run(&model, &fx, Some(&mut capture));
    assert!(max_abs_diff(&hooked, &plain) <= 1e-5);
    for layer in &wanted {
        let (kind, probs) = capture
            .seen
            .get(layer)
            .unwrap_or_else(|| panic!("{name}: {layer} never called"));
        let want_kind = if layer.ends_with("attn1") {
            AttnKind::SelfAttn
        } else {
            AttnKind::CrossAttn
        };
        assert_eq!(*kind, want_kind, "{layer}");
        let err = max_abs_diff(probs, &fx[&format!("probs.{layer}")]);
        println!("{name}: {layer} probs max abs error {err:e}");
        assert!(err <= 1e-4, "{name}: {layer} probabilities differ by {err}");
    }
    // Every transformer block reports one self- and one cross-attention call with its latent size.
    let (h, w) = (fx["sample"].dims()[2], fx["sample"].dims()[3]);
    let first = &capture.calls[0];
    assert_eq!(
        first.0,
        "down_blocks.0.attentions.0.transformer_blocks.0.attn1"
    );
    assert_eq!((first.2, first.3), (h, w));
    let selfs = capture
        .calls
        .iter()
        .filter(|c| c.1 == AttnKind::SelfAttn)
        .count();
    assert_eq!(selfs * 2, capture.calls.len());

    let maps: HashMap<String, Tensor> = layers_with_prefix(&fx, "hook.maps.")
        .into_iter()
        .map(|l| (l.clone(), fx[&format!("hook.maps.{l}")].clone()))
        .collect();
    assert!(!maps.is_empty());
    let replaced = run(&model, &fx, Some(&mut ReplaceMaps(maps)));
    let err = max_abs_diff(&replaced, &fx["hook.noise_pred"]);
    let effect = max_abs_diff(&replaced, &plain);
    println!("{name}: replaced-maps output max abs error {err:e} (change from plain {effect:.3})");
    assert!(effect > 1e-2, "replacing maps should change the output");
    assert!(
        err <= 1e-4,
        "{name}: hook output differs from diffusers' processor by {err}"
    );

    let swapped = run(&model, &fx, Some(&mut SwapLastKv));
    let err = max_abs_diff(&swapped, &fx["swap.noise_pred"]);
    println!("{name}: swapped-kv output max abs error {err:e}");
    assert!(max_abs_diff(&swapped, &plain) > 1e-2);
    assert!(
        err <= 1e-4,
        "{name}: K/V swap differs from diffusers' processor by {err}"
    );
}

#[test]
fn tiny_lcm_matches_diffusers() {
    check_model("tiny-lcm");
}

#[test]
fn tiny_ip2p_from_f16_matches_diffusers() {
    check_model("tiny-ip2p");
}

/// With bf16 products (on a CPU with AVX512-BF16) the tiny UNets' noise predictions stay within bf16's
/// rounding of diffusers' f32 ones: relative L2 ≤ 1e-2 (PyTorch's own bf16 SD 1.5 UNet: 1.2 % against
/// its f32), and above 1e-5, so bf16 products did run. A model loaded under bf16 products keeps only its
/// weights' bf16 pairs and gives the very same output. The f32 path afterwards is unchanged.
#[test]
fn tiny_unets_with_bf16_products_match_diffusers_within_bf16() {
    for name in ["tiny-lcm", "tiny-ip2p"] {
        let model = load_model(name);
        let fx = load_fixture(name);
        let Some((out, stored_once)) =
            in_bf16(|| (run(&model, &fx, None), run(&load_model(name), &fx, None)))
        else {
            return;
        };
        assert_eq!(max_abs_diff(&out, &stored_once), 0.0, "{name}: stored once");
        let rel = relative_l2(&out, &fx["noise_pred"]);
        println!("{name}: bf16 noise_pred relative L2 {rel:.2e}");
        assert!(rel <= 1e-2 && rel > 1e-5, "{name}: relative L2 {rel}");
        let again = run(&model, &fx, None);
        assert!(max_abs_diff(&again, &fx["noise_pred"]) <= 1e-4);
    }
}

#[test]
fn lcm_without_condition_matches_diffusers() {
    let model = load_model("tiny-lcm");
    let fx = load_fixture("tiny-lcm");
    let out = model
        .forward(
            &fx["sample"],
            &fx["timesteps"],
            &fx["encoder_hidden_states"],
            None,
            None,
        )
        .unwrap();
    let err = max_abs_diff(&out, &fx["nocond.noise_pred"]);
    assert!(
        err <= 1e-4,
        "output without timestep_cond differs from diffusers by {err}"
    );
    assert!(
        max_abs_diff(&out, &fx["noise_pred"]) > 1e-2,
        "the condition must matter"
    );
}

/// One definition on both devices: the tiny UNets on the GPU (lavapipe in CI) match the CPU to f32
/// precision (to 1e-2 with f16 weights) without a hook (flash attention), with a hook that reads every
/// probability map (explicit probabilities, read back to the CPU) and with one that rewrites K/V (mutual
/// self-attention).
#[test]
fn tiny_unet_on_gpu_matches_cpu() {
    for (gpu, tolerance) in common::gpus_or_skip() {
        for name in ["tiny-lcm", "tiny-ip2p"] {
            let model = load_model(name);
            let fx = load_fixture(name);
            let on_gpu_device = diffusion::device::Device::Gpu(gpu.clone());
            let on = |hook: Option<&mut dyn AttentionHook>, device: &diffusion::device::Device| {
                model
                    .forward_on(
                        &fx["sample"],
                        &fx["timesteps"],
                        &fx["encoder_hidden_states"],
                        fx.get("timestep_cond"),
                        hook,
                        device,
                    )
                    .unwrap()
            };
            let plain = common::relative_error(
                &on(None, &on_gpu_device),
                &on(None, &diffusion::device::Device::Cpu),
            );
            let capture = || Capture {
                wanted: layers_with_prefix(&fx, "probs.").into_iter().collect(),
                seen: HashMap::new(),
                calls: Vec::new(),
            };
            let (mut on_cpu, mut on_gpu) = (capture(), capture());
            let want = on(Some(&mut on_cpu), &diffusion::device::Device::Cpu);
            let maps = common::relative_error(&on(Some(&mut on_gpu), &on_gpu_device), &want);
            assert_eq!(
                on_cpu.calls, on_gpu.calls,
                "{name}: the hook sees the same calls"
            );
            let mut map_err = 0f32;
            for (layer, (_, probs)) in &on_cpu.seen {
                map_err = map_err.max(common::relative_error(&on_gpu.seen[layer].1, probs));
            }
            let swapped = common::relative_error(
                &on(Some(&mut SwapLastKv), &on_gpu_device),
                &on(Some(&mut SwapLastKv), &diffusion::device::Device::Cpu),
            );
            let precision = gpu.precision();
            println!(
            "{name} on {}, {precision} weights: relative errors plain {plain:.2e}, hooked {maps:.2e}, maps {map_err:.2e}, swapped K/V {swapped:.2e}",
            gpu.name()
        );
            for (what, err) in [
                ("plain", plain),
                ("hooked", maps),
                ("maps", map_err),
                ("swapped", swapped),
            ] {
                assert!(
                    err <= tolerance,
                    "{name} {what}, {precision} weights: relative error {err}"
                );
            }
        }
    }
}

/// A hook that has seen all it needs after the first `wanted` attention calls.
struct Observer {
    wanted: usize,
    seen: Vec<String>,
}

impl AttentionHook for Observer {
    fn qkv(&mut self, call: &AttnCall, qkv: Qkv) -> Result<Qkv> {
        self.seen.push(call.layer.to_string());
        Ok(qkv)
    }

    fn finished(&self) -> bool {
        self.seen.len() >= self.wanted
    }
}

/// An observed pass ends at the end of the block where its hook has seen all it wants (no later
/// attention call runs, no prediction); a plain pass with the same hook runs to its end.
#[test]
fn an_observed_pass_stops_once_its_hook_is_finished() {
    let model = load_model("tiny-lcm");
    let fx = load_fixture("tiny-lcm");
    let mut all = Observer {
        wanted: usize::MAX,
        seen: Vec::new(),
    };
    let full = run(&model, &fx, Some(&mut all));
    let mid = all
        .seen
        .iter()
        .position(|l| l.starts_with("mid_block"))
        .expect("the tiny UNet's mid block attends");
    let observed = |wanted: usize| {
        let mut hook = Observer {
            wanted,
            seen: Vec::new(),
        };
        let out = model
            .forward_observed(
                &fx["sample"],
                &fx["timesteps"],
                &fx["encoder_hidden_states"],
                fx.get("timestep_cond"),
                &mut hook,
                &diffusion::device::Device::Cpu,
            )
            .unwrap();
        (out, hook.seen)
    };
    // Finished inside the mid block: the pass ends with it, before the up blocks.
    let (out, seen) = observed(mid + 1);
    assert!(out.is_none());
    assert_eq!(seen, all.seen[..seen.len()]);
    assert!(seen.last().unwrap().starts_with("mid_block"), "{seen:?}");
    // Never finished: the whole pass and its prediction, as a plain one.
    let (out, seen) = observed(usize::MAX);
    assert_eq!(seen, all.seen);
    assert_eq!(max_abs_diff(&out.unwrap(), &full), 0.0);
    // A plain pass does not ask.
    let mut early = Observer {
        wanted: 1,
        seen: Vec::new(),
    };
    run(&model, &fx, Some(&mut early));
    assert_eq!(early.seen, all.seen);
}
