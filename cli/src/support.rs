//! `lbctl kubernetes-support`: where the clusters' Kubernetes minor stands in EKS's standard
//! support, so an upgrade is planned before a cluster starts paying extended support.

use clap::Args;
use lb_infra::support;

/// `lbctl kubernetes-support` options.
#[derive(Debug, Args)]
pub struct KubernetesSupport {
    /// The minor to check (default: `infra/cluster.yaml`'s `KubernetesVersion`, as built in).
    #[arg(long)]
    pub minor: Option<String>,
}

/// Prints the standing; exit 1 when an operator must act (within 60 days of the end, past it,
/// or no date known).
pub fn run(args: KubernetesSupport) -> anyhow::Result<u8> {
    let minor = match args.minor {
        Some(minor) => minor,
        None => support::template_minor().ok_or_else(|| {
            anyhow::anyhow!("infra/cluster.yaml has no KubernetesVersion default")
        })?,
    };
    let today = time::OffsetDateTime::now_utc().date();
    let standing = support::standing(&minor, today);
    outln!("{}", support::describe(&minor, standing));
    Ok(u8::from(standing.needs_action()))
}
