//! The work ledger: units of work per stage of an edit (UNet samples, lifting rounds, fit steps, codec
//! passes, reads from the networks' device), counted as a run does them and planned before it starts,
//! so a stage's time can be read per unit of work on any machine; on a GPU also the kernel launches and
//! device reads each stage made.

use gpu::traffic::DeviceTraffic;
use serde::{Deserialize, Serialize};

/// Units of work of one stage.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct StageWork {
    /// UNet calls, and the samples (latent rows) they computed in all.
    pub unet_calls: usize,
    pub unet_samples: usize,
    /// Lifting rounds (all views' maps lifted onto the Gaussians once), and the views rendered back.
    pub lifting_rounds: usize,
    pub render_backs: usize,
    /// Optimiser steps of scene fits (ECM's two fits count one each).
    pub fit_steps: usize,
    /// Images through the autoencoder.
    pub vae_encodes: usize,
    pub vae_decodes: usize,
    /// Attention maps the editing logic reads from the UNet's device to the host, and their bytes (free
    /// on the CPU; a copy on a GPU).
    pub map_reads: usize,
    pub map_read_bytes: u64,
    /// On a GPU, everything the stage asked of the device: kernels launched, and reads of device
    /// buffers back to the host (the map reads among them) with their bytes. 0 on the CPU, and not
    /// planned (the plan counts the units of work above; these say what each unit costs a card).
    pub launches: u64,
    pub device_reads: u64,
    pub device_read_bytes: u64,
}

impl StageWork {
    fn add(&mut self, o: &StageWork) {
        self.unet_calls += o.unet_calls;
        self.unet_samples += o.unet_samples;
        self.lifting_rounds += o.lifting_rounds;
        self.render_backs += o.render_backs;
        self.fit_steps += o.fit_steps;
        self.vae_encodes += o.vae_encodes;
        self.vae_decodes += o.vae_decodes;
        self.map_reads += o.map_reads;
        self.map_read_bytes += o.map_read_bytes;
        self.launches += o.launches;
        self.device_reads += o.device_reads;
        self.device_read_bytes += o.device_read_bytes;
    }

    /// Adds what the device was asked while the stage ran.
    pub fn add_traffic(&mut self, t: DeviceTraffic) {
        self.launches += t.launches;
        self.device_reads += t.reads;
        self.device_read_bytes += t.read_bytes;
    }
}

/// Units of work per stage of an edit (the stages of [`crate::consistency::StageTimes`] plus the fit).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct WorkLedger {
    pub encode: StageWork,
    pub ccm: StageWork,
    pub unet: StageWork,
    pub ecm: StageWork,
    pub blend: StageWork,
    pub decode: StageWork,
    /// The editing loop's own fit of the scene to the guidance.
    pub fit: StageWork,
}

impl WorkLedger {
    pub fn add(&mut self, o: &WorkLedger) {
        for (a, b) in self.stages_mut().into_iter().zip(o.stages()) {
            a.add(&b);
        }
    }

    fn stages(&self) -> [StageWork; 7] {
        [
            self.encode,
            self.ccm,
            self.unet,
            self.ecm,
            self.blend,
            self.decode,
            self.fit,
        ]
    }

    fn stages_mut(&mut self) -> [&mut StageWork; 7] {
        [
            &mut self.encode,
            &mut self.ccm,
            &mut self.unet,
            &mut self.ecm,
            &mut self.blend,
            &mut self.decode,
            &mut self.fit,
        ]
    }

    /// Every stage's work summed.
    pub fn total(&self) -> StageWork {
        let mut t = StageWork::default();
        for s in self.stages() {
            t.add(&s);
        }
        t
    }

    /// One line of the totals, e.g. for the printed plan and the report.
    pub fn describe(&self) -> String {
        let t = self.total();
        let mut line = format!(
            "{} UNet samples in {} calls, {} lifting rounds ({} render-backs), {} fit steps, \
             {} VAE encodes, {} decodes",
            t.unet_samples,
            t.unet_calls,
            t.lifting_rounds,
            t.render_backs,
            t.fit_steps,
            t.vae_encodes,
            t.vae_decodes
        );
        if t.map_reads > 0 {
            line += &format!(
                ", {} map reads ({:.1} MB)",
                t.map_reads,
                t.map_read_bytes as f64 / 1e6
            );
        }
        if t.launches > 0 || t.device_reads > 0 {
            line += &format!(
                "; on the device {} kernel launches, {} reads ({:.1} MB)",
                t.launches,
                t.device_reads,
                t.device_read_bytes as f64 / 1e6
            );
        }
        line
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_add_up() {
        let mut a = WorkLedger::default();
        a.unet.unet_samples = 5;
        a.ccm.unet_samples = 3;
        a.ccm.lifting_rounds = 2;
        let mut b = a.clone();
        b.fit.fit_steps = 7;
        a.add(&b);
        assert_eq!(a.unet.unet_samples, 10);
        assert_eq!(a.total().unet_samples, 16);
        assert_eq!(a.total().fit_steps, 7);
        assert!(
            a.describe().starts_with("16 UNet samples"),
            "{}",
            a.describe()
        );
        assert!(
            !a.describe().contains("on the device"),
            "nothing on a device"
        );
        a.ecm.add_traffic(DeviceTraffic {
            launches: 40,
            reads: 2,
            read_bytes: 3_000_000,
        });
        a.decode.add_traffic(DeviceTraffic {
            launches: 2,
            ..Default::default()
        });
        assert_eq!(a.total().launches, 42);
        assert!(
            a.describe()
                .ends_with("; on the device 42 kernel launches, 2 reads (3.0 MB)"),
            "{}",
            a.describe()
        );
    }
}
