//! Amazon States Language data flow, as AWS Step Functions evaluates it: JSONPath and
//! reference paths, payload templates (`Parameters`, `ResultSelector`), intrinsic functions
//! and the InputPath/ResultPath/OutputPath pipeline.
//!
//! One implementation serves the Job template renderer and the embedded state-machine
//! executor. Everything is parsed once (definition errors are [`LoadError`]s, found before
//! anything runs) and evaluated many times (evaluation errors are [`AslError`]s carrying the
//! Step Functions error names and AWS-shaped messages).
//!
//! ```
//! use lb_asl::{Env, Template};
//! use serde_json::json;
//!
//! let params = Template::compile(&json!({
//!     "greeting.$": "States.Format('Hello, {}!', $.name)",
//!     "who.$": "$.name",
//!     "static": "kept",
//! })).unwrap();
//! let out = params.render(&json!({"name": "Arnav"}), &Env::none()).unwrap();
//! assert_eq!(out, json!({"greeting": "Hello, Arnav!", "who": "Arnav", "static": "kept"}));
//! ```

mod dataflow;
mod error;
pub mod intrinsic;
mod path;
mod random;
mod template;

use serde_json::Value;

pub use dataflow::{DataFlow, ResultPath, Selection};
pub use error::{preview, AslError, LoadError, INPUT_PREVIEW_CHARS};
pub use intrinsic::{Call, Function};
pub use path::{Path, RefStep, ReferencePath, Root};
pub use random::RandomSource;
pub use template::{DynamicField, Template};

/// What an evaluation may read besides its input: the context object (`$$`) and the random
/// source of `States.MathRandom` and `States.UUID`.
#[derive(Debug, Clone, Copy)]
pub struct Env<'a> {
    /// The context object (`null` when there is none).
    pub context: &'a Value,
    /// Random numbers for `States.MathRandom` (without a seed) and `States.UUID`.
    pub random: &'a RandomSource,
}

static NO_CONTEXT: Value = Value::Null;

impl Env<'static> {
    /// No context object; the process-wide random source.
    pub fn none() -> Env<'static> {
        Env {
            context: &NO_CONTEXT,
            random: RandomSource::global(),
        }
    }
}

impl<'a> Env<'a> {
    /// The given context object; the process-wide random source.
    pub fn with_context(context: &'a Value) -> Env<'a> {
        Env {
            context,
            random: RandomSource::global(),
        }
    }

    /// The same environment with another random source (a seeded one in tests).
    pub fn random(self, random: &'a RandomSource) -> Env<'a> {
        Env { random, ..self }
    }
}
