//! Compiles `proto/bgkmap/v1/bgkmap.proto` with protox (pure Rust, no system `protoc`) and
//! writes the descriptor set used by gRPC reflection.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
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
