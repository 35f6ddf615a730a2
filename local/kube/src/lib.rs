//! A local Kubernetes API server (`batch/v1` Jobs, `v1` Pods, logs, discovery) whose pods run
//! as local processes: kube-rs and the real kubectl work against it unchanged.

mod api;
mod config;
mod error;
mod imagemap;
mod kubeconfig;
pub mod objects;
mod runtime;
pub mod selector;
mod server;
pub mod status;
mod store;

pub use api::Outage;
pub use config::{Config, Isolation, Timing};
pub use error::{Error, Result};
pub use imagemap::{ImageEntry, ImageMap, ImageMapError, Pull};
pub use kubeconfig::kubeconfig_yaml;
pub use runtime::disk::{PodDisk, LAYER_MOUNT};
pub use runtime::scheduler::{
    autoscaler_word, gpu_request, gpu_uuid, selects, AUTOSCALER, INSUFFICIENT_GPU, NOT_TRIGGERED,
    SELECTOR_MISMATCH, UNMODELLED_GPUS,
};
pub use server::{LocalKube, PodRunner};
