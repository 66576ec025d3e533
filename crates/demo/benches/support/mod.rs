//! Argument parsing shared by this crate's bench binaries (`mod support;` in each; a folder, so that
//! cargo does not take it for a bench of its own).

/// The value after `name` on the command line, if any.
pub fn arg_value(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

/// The whole number after `name`, or `default`; a bench stops with a message on anything else.
pub fn number(args: &[String], name: &str, default: usize) -> usize {
    arg_value(args, name).map_or(default, |v| {
        v.parse()
            .unwrap_or_else(|_| panic!("{name} takes a whole number"))
    })
}
