//! `kairos-fuzz TARGET`: one afl.rs fuzz loop over `kairos_server::fuzz_targets::TARGETS`.
//! `scripts/fuzz.sh` builds it with `cargo afl build --release` and runs one `cargo afl fuzz`
//! per target.

fn main() {
    let name = std::env::args().nth(1).unwrap_or_default();
    let Some(&(_, target)) = kairos_server::fuzz_targets::TARGETS
        .iter()
        .find(|(n, _)| *n == name)
    else {
        let names: Vec<&str> = kairos_server::fuzz_targets::TARGETS
            .iter()
            .map(|(n, _)| *n)
            .collect();
        eprintln!("usage: kairos-fuzz TARGET, one of: {}", names.join(", "));
        std::process::exit(2);
    };
    afl::fuzz!(|data: &[u8]| {
        target(data);
    });
}
