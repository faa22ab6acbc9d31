//! The integration tests, one binary with a module per area, so the crate is linked once for
//! all of them. Most start the real `bgkmap` binary ([`common`] holds the helpers for that);
//! `format_fixture` opens the checked-in map files with the library alone. Every module is gated
//! on the features it needs, so `cargo test --no-default-features` still builds.

#[cfg(feature = "cli")]
mod common;

mod cli;
mod cli_durable;
mod cli_errors;
mod concurrency;
mod crash;
mod durable;
mod format_fixture;
mod grpc;
mod integrity;
mod limits;
#[cfg(feature = "cli")]
mod plots;
mod sample_data;
mod viewer_http;
mod watch;
mod zenoh;
