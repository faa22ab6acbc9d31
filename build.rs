//! Compiles `proto/bgkmap/v1/bgkmap.proto` with protox (pure Rust, no system `protoc`) and
//! writes the descriptor set used by gRPC reflection; and tells the tests whether the sample
//! data is there (see [`sample_data_cfg`]).

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    sample_data_cfg();
    if std::env::var_os("CARGO_FEATURE_SERVER").is_none() {
        return Ok(());
    }
    let fds = protox::compile(["bgkmap/v1/bgkmap.proto"], ["proto"])?;
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("bgkmap_descriptor.bin"), prost::Message::encode_to_vec(&fds))?;
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .codec_path("crate::api::codec::StrictCodec")
        .compile_fds(fds)?;
    Ok(())
}

/// Sets `cfg(bgkmap_sample_data)` when la3dm's sample data (`../shared/data/la3dm/sim_structured`
/// beside the checkout) exists. Tests that read it are ignored without it, so they show up as
/// skipped instead of passing without having run; `sample_data::present_when_ci_is_set` fails
/// when `CI` is set and the data is missing. `BGKMAP_SAMPLE_DATA=absent` builds as if it were
/// missing, to try both ways on a machine that has it.
fn sample_data_cfg() {
    println!("cargo::rustc-check-cfg=cfg(bgkmap_sample_data)");
    println!("cargo::rerun-if-env-changed=BGKMAP_SAMPLE_DATA");
    let root = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_default());
    let shared = root.join("../shared");
    let data = shared.join("data/la3dm/sim_structured");
    // Cargo reruns this script (and rebuilds the crate) on every build while a watched path is
    // missing, so watch the deepest part of the path that exists: adding or removing the data
    // changes it. Without even `../shared`, nothing is watched; touch build.rs after linking it.
    let watched = data.ancestors().take_while(|p| p.starts_with(&shared)).find(|p| p.exists());
    if let Some(watched) = watched {
        println!("cargo::rerun-if-changed={}", watched.display());
    }
    let forced_absent = std::env::var_os("BGKMAP_SAMPLE_DATA").is_some_and(|v| v == "absent");
    if !forced_absent && data.is_dir() {
        println!("cargo::rustc-cfg=bgkmap_sample_data");
    }
}
