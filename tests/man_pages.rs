//! The man pages in `man/` are generated from the clap definitions (`colf::cli::commands()`),
//! so they say what `--help` says. This test fails when a page is missing or stale;
//! `COLF_UPDATE_MAN=1 cargo test --release --test man_pages` (or `make man`) rewrites them.

use std::path::Path;

/// Renders the page of `cmd` and, for a command with subcommands, one page per subcommand
/// (`colf-cameras-orbit.1`), returning (file name, bytes).
fn pages(cmd: clap::Command) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let name = cmd.get_name().to_string();
    for sub in cmd.get_subcommands() {
        let sub_name = format!("{name}-{}", sub.get_name());
        // clap's names are 'static; a test process may leak a few short strings.
        let static_name: &'static str = Box::leak(sub_name.clone().into_boxed_str());
        let mut sub = sub.clone().name(static_name);
        if let Some(v) = cmd.get_version() {
            sub = sub.version(v.to_string().leak() as &'static str);
        }
        let mut bytes = Vec::new();
        clap_mangen::Man::new(sub).render(&mut bytes).unwrap();
        out.push((format!("{sub_name}.1"), bytes));
    }
    let mut bytes = Vec::new();
    clap_mangen::Man::new(cmd).render(&mut bytes).unwrap();
    out.push((format!("{name}.1"), bytes));
    out
}

#[test]
fn man_pages_match_the_command_definitions() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("man");
    let update = std::env::var_os("COLF_UPDATE_MAN").is_some();
    let mut stale = Vec::new();
    for cmd in colf::cli::commands() {
        for (file, bytes) in pages(cmd) {
            let path = dir.join(&file);
            if update {
                std::fs::create_dir_all(&dir).unwrap();
                std::fs::write(&path, &bytes).unwrap();
            } else if std::fs::read(&path).ok().as_deref() != Some(&bytes[..]) {
                stale.push(file);
            }
        }
    }
    assert!(
        stale.is_empty(),
        "man pages missing or stale: {stale:?}; run `make man`"
    );
}
