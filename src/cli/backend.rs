//! `volux backend`: is this backend usable here?

use clap::Args;
use volux_model::backend::{BackendKind, self_check};

#[derive(Debug, Args)]
pub struct BackendArgs {
    /// Backend to check: cpu or wgpu.
    #[arg(long, default_value = "cpu")]
    pub backend: BackendKind,
}

pub fn run(args: BackendArgs) -> anyhow::Result<()> {
    for kind in BackendKind::ALL {
        println!(
            "{:<5} {}",
            kind.name(),
            if kind.is_compiled() {
                "compiled in"
            } else {
                "not compiled in"
            }
        );
    }
    let check = self_check(args.backend)?;
    println!(
        "{}: ok on {} (forward differs from CPU by {:.1e}, gradient by {:.1e})",
        args.backend, check.device, check.forward_error, check.gradient_error
    );
    Ok(())
}
