//! Showing a run to people: the HTML report (`report`), the interactive 3D before/after viewer it embeds
//! (`viewer`, also `vcedit view`), the turntable GIF (`gif`) and attention and mask images (`viz`).

pub mod gif;
pub mod report;
pub mod viewer;
pub mod viz;

use maud::{html, Markup, PreEscaped, DOCTYPE};

/// A standalone HTML page: its title, its style sheet and its body.
fn html_page(title: &str, css: &str, body: Markup) -> String {
    html! {
        (DOCTYPE)
        html lang="en" {
            head {
                meta charset="utf-8";
                meta name="viewport" content="width=device-width, initial-scale=1";
                title { (title) }
                style { (PreEscaped(css)) }
            }
            body { (body) }
        }
    }
    .into_string()
}

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
