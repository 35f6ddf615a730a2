//! Definitions and inputs are untrusted: any text and any JSON give a value or a named error,
//! never a panic.

use lb_asl::{Call, Env, Path, RandomSource, ReferencePath, ResultPath, Template};
use proptest::prelude::*;
use serde_json::{json, Value};

fn any_json() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::from),
        any::<i64>().prop_map(Value::from),
        (-1e12f64..1e12).prop_map(Value::from),
        ".{0,12}".prop_map(Value::from),
        Just(json!("{} and {}")),
    ];
    leaf.prop_recursive(3, 24, 4, |inner| {
        prop_oneof![
            proptest::collection::vec(inner.clone(), 0..4).prop_map(Value::from),
            proptest::collection::btree_map("[a-c]{1,2}", inner, 0..4)
                .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

const CALLS: &[&str] = &[
    "States.Format($.a, $.b)",
    "States.Format('{} {}', $.a, $.b)",
    "States.StringToJson($.a)",
    "States.JsonToString($.a)",
    "States.ArrayPartition($.a, $.b)",
    "States.ArrayContains($.a, $.b)",
    "States.ArrayRange($.a, $.b, $.c)",
    "States.ArrayGetItem($.a, $.b)",
    "States.ArrayLength($.a)",
    "States.ArrayUnique($.a)",
    "States.Base64Encode($.a)",
    "States.Base64Decode($.a)",
    "States.Hash($.a, $.b)",
    "States.JsonMerge($.a, $.b, $.c)",
    "States.MathRandom($.a, $.b)",
    "States.MathRandom($.a, $.b, $.c)",
    "States.MathAdd($.a, $.b)",
    "States.StringSplit($.a, $.b)",
    "States.Array($..a, $.*, $.a[-1:])",
];

proptest! {
    #[test]
    fn any_text_parses_or_is_refused_with_a_name(text in ".{0,40}", tail in "[$.\\[\\]'a-c0-9*:,()? -]{0,20}") {
        for candidate in [text.clone(), format!("${tail}"), format!("States.Array({tail})"), format!("States.Format('{text}')")] {
            if let Err(e) = Path::parse(&candidate) { prop_assert!(!e.name().is_empty()); }
            if let Err(e) = ReferencePath::parse(&candidate) { prop_assert!(!e.name().is_empty()); }
            if let Err(e) = Call::parse(&candidate) { prop_assert!(!e.name().is_empty()); }
        }
    }

    #[test]
    fn every_function_gives_a_value_or_a_named_error_on_any_input(
        a in any_json(), b in any_json(), c in any_json(),
    ) {
        let input = json!({"a": a, "b": b, "c": c});
        let random = RandomSource::seeded(1);
        let env = Env::none().random(&random);
        for text in CALLS {
            let t = Template::compile(&json!({"out.$": text})).unwrap();
            if let Err(e) = t.render(&input, &env) {
                prop_assert!(e.name().starts_with("States."), "{e}");
            }
        }
        for path in ["$.a", "$.a.b", "$.a[0]", "$.b[-1].c"] {
            let rp = ResultPath::from_field(Some(&json!(path))).unwrap();
            if let Err(e) = rp.apply(input.clone(), json!(1)) {
                prop_assert_eq!(e.name(), "States.ResultPathMatchFailure");
            }
        }
    }
}
