//! Stable error names declared once: a table per error enum gives its `name()`, whether it is
//! transient, and the lists of both that the state machine's test checks the definition against.
//!
//! ```
//! #[derive(Debug)]
//! enum Inner { Slow }
//! lb_domain::error_names!(Inner { Slow => "InnerSlow" [transient] });
//!
//! #[derive(Debug)]
//! enum Outer { Bad { why: String }, Wrapped(Inner) }
//! lb_domain::error_names!(Outer { Bad => "OuterBad" } wraps { Wrapped => Inner });
//!
//! assert_eq!(Outer::Wrapped(Inner::Slow).name(), "InnerSlow");
//! assert!(Outer::Wrapped(Inner::Slow).is_transient());
//! assert!(!Outer::Bad { why: String::new() }.is_transient());
//! assert_eq!(Outer::names(), ["OuterBad", "InnerSlow"]);
//! assert_eq!(Outer::transient_names(), ["InnerSlow"]);
//! ```

/// Implements `name()`, `is_transient()`, `names()` and `transient_names()` on an error enum
/// from one table: `Variant | Other => "Name"` (with `[transient]` when retrying may help),
/// then, after the table, `wraps { Variant => Inner }` for variants that hold another named
/// error (as their one field) and take its name.
#[macro_export]
macro_rules! error_names {
    (
        $ty:ident {
            $( $($variant:ident)|+ => $name:literal $([$transient:ident])? );* $(;)?
        }
        $(wraps { $( $($via:ident)|+ => $inner:ty );* $(;)? })?
    ) => {
        impl $ty {
            /// The stable PascalCase name the state machine matches.
            #[allow(unreachable_patterns)]
            pub fn name(&self) -> &'static str {
                match self {
                    $( $(Self::$variant { .. })|+ => $name, )*
                    $($( $(Self::$via(inner))|+ => inner.name(), )*)?
                }
            }

            /// Whether the same call may succeed later (the state machine retries these).
            #[allow(unreachable_patterns)]
            pub fn is_transient(&self) -> bool {
                match self {
                    $( $(Self::$variant { .. })|+ => $crate::__transient!($($transient)?), )*
                    $($( $(Self::$via(inner))|+ => inner.is_transient(), )*)?
                }
            }

            /// Every name this error can carry, its own first, then those of the errors it
            /// wraps.
            pub fn names() -> ::std::vec::Vec<&'static str> {
                #[allow(unused_mut)]
                let mut names = ::std::vec![$($name),*];
                $($( names.extend(<$inner>::names()); )*)?
                $crate::errors::unique(names)
            }

            /// The names of [`Self::names`] that are transient.
            pub fn transient_names() -> ::std::vec::Vec<&'static str> {
                #[allow(unused_mut)]
                let mut names: ::std::vec::Vec<&'static str> =
                    [$(($name, $crate::__transient!($($transient)?))),*]
                        .into_iter()
                        .filter_map(|(name, transient)| transient.then_some(name))
                        .collect();
                $($( names.extend(<$inner>::transient_names()); )*)?
                $crate::errors::unique(names)
            }
        }
    };
}

/// `[transient]` or nothing, as a bool (used by [`error_names!`]).
#[doc(hidden)]
#[macro_export]
macro_rules! __transient {
    () => {
        false
    };
    (transient) => {
        true
    };
}

/// `names` without repeats, in first-seen order (two variants may share a name).
pub fn unique(names: Vec<&'static str>) -> Vec<&'static str> {
    let mut out: Vec<&'static str> = Vec::with_capacity(names.len());
    for name in names {
        if !out.contains(&name) {
            out.push(name);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    #[derive(Debug)]
    enum Leaf {
        Slow(()),
        Bad { _why: &'static str },
        Odd,
        Same,
    }
    crate::error_names!(Leaf {
        Slow => "LeafSlow" [transient];
        Bad | Odd => "LeafBad";
        Same => "LeafSlow" [transient]
    });

    #[derive(Debug)]
    enum Top {
        Own,
        Wrapped(Leaf),
        AlsoWrapped(Leaf),
    }
    crate::error_names!(Top { Own => "TopOwn" } wraps { Wrapped | AlsoWrapped => Leaf });

    #[test]
    fn tuple_struct_and_unit_variants_take_their_names_and_wrapped_ones_their_inner_name() {
        assert_eq!(Leaf::Slow(()).name(), "LeafSlow");
        assert_eq!(Leaf::Bad { _why: "x" }.name(), "LeafBad");
        assert_eq!(Leaf::Odd.name(), "LeafBad");
        assert!(Leaf::Same.is_transient());
        assert_eq!(Top::Own.name(), "TopOwn");
        assert_eq!(Top::AlsoWrapped(Leaf::Odd).name(), "LeafBad");
        assert!(Top::Wrapped(Leaf::Slow(())).is_transient());
        assert!(!Top::Wrapped(Leaf::Odd).is_transient());
        assert!(!Top::Own.is_transient());
    }

    #[test]
    fn the_lists_hold_each_name_once_with_the_wrapped_errors_names() {
        assert_eq!(Leaf::names(), ["LeafSlow", "LeafBad"]);
        assert_eq!(Leaf::transient_names(), ["LeafSlow"]);
        assert_eq!(Top::names(), ["TopOwn", "LeafSlow", "LeafBad"]);
        assert_eq!(Top::transient_names(), ["LeafSlow"]);
    }
}
