//! Showing a run to people: the HTML report (`report`), the interactive 3D before/after viewer it embeds
//! (`viewer`, also `vcedit view`), the turntable GIF (`gif`) and attention and mask images (`viz`).

pub mod gif;
pub mod report;
pub mod viewer;
pub mod viz;

/// "1 view", "2 views": a count with its noun in the right number.
pub fn count(n: usize, singular: &str, plural: &str) -> String {
    format!("{n} {}", if n == 1 { singular } else { plural })
}

#[cfg(test)]
mod tests {
    #[test]
    fn counts_agree_with_their_nouns() {
        assert_eq!(super::count(1, "view", "views"), "1 view");
        assert_eq!(super::count(0, "view", "views"), "0 views");
        assert_eq!(super::count(2, "UNet pass", "UNet passes"), "2 UNet passes");
    }
}
