//! Inside the Jobs: the plan of pairs, the marker protocol, what logcopy may upload, and the
//! participant's text made fit to show.

pub mod logtail;
pub mod plan;
pub mod protocol;
pub mod uploads;
