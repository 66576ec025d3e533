//! Free memory of the card behind an adapter, read when the device opens so that a run can be planned
//! (and refused) before it allocates anything.
//!
//! wgpu has no query for free memory (gfx-rs/wgpu#2447), so it comes from the vendor's own interface,
//! found by the card's PCI address: NVML for NVIDIA cards (`libnvidia-ml`, loaded at run time, so the
//! build needs nothing and a machine without the driver library reports "unknown"), and the amdgpu
//! driver's VRAM counters in sysfs for AMD cards. Other cards (Intel, Apple), software adapters and
//! other systems report unknown, and the callers then fall back to a fixed share.

use std::path::Path;

/// Where the amdgpu driver publishes each card's VRAM counters.
const SYSFS_PCI_DEVICES: &str = "/sys/bus/pci/devices";

/// The card's free memory in bytes, when its vendor's interface reports it. `pci` is the
/// `domain:bus:device.function` address, in hex as Linux and NVML write it.
pub(crate) fn free_bytes(pci: &str) -> Option<u64> {
    nvml_free_bytes(pci).or_else(|| amdgpu_free_bytes(Path::new(SYSFS_PCI_DEVICES), pci))
}

fn nvml_free_bytes(pci: &str) -> Option<u64> {
    let nvml = nvml_wrapper::Nvml::init().ok()?;
    let device = nvml.device_by_pci_bus_id(pci).ok()?;
    Some(device.memory_info().ok()?.free)
}

/// `mem_info_vram_total − mem_info_vram_used` of the card at `pci` under `devices` (sysfs).
fn amdgpu_free_bytes(devices: &Path, pci: &str) -> Option<u64> {
    let read = |name: &str| -> Option<u64> {
        std::fs::read_to_string(devices.join(pci).join(name))
            .ok()?
            .trim()
            .parse()
            .ok()
    };
    let total = read("mem_info_vram_total")?;
    let used = read("mem_info_vram_used")?;
    Some(total.saturating_sub(used))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn amdgpu_counters_give_free_vram() {
        let root = std::env::temp_dir().join(format!("vcedit-sysfs-{}", std::process::id()));
        let card = root.join("0000:03:00.0");
        std::fs::create_dir_all(&card).unwrap();
        std::fs::write(card.join("mem_info_vram_total"), "17163091968\n").unwrap();
        std::fs::write(card.join("mem_info_vram_used"), "1073741824\n").unwrap();
        assert_eq!(
            amdgpu_free_bytes(&root, "0000:03:00.0"),
            Some(17163091968 - 1073741824)
        );
        // Another card, or a card whose driver has no counters (not amdgpu): unknown.
        assert_eq!(amdgpu_free_bytes(&root, "0000:04:00.0"), None);
        std::fs::write(card.join("mem_info_vram_used"), "garbage").unwrap();
        assert_eq!(amdgpu_free_bytes(&root, "0000:03:00.0"), None);
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn no_driver_interface_is_unknown() {
        // No card at this address: NVML (absent here, or present without this card) and sysfs both
        // answer nothing, and nothing panics.
        assert_eq!(free_bytes("7fff:ff:1f.7"), None);
    }
}
