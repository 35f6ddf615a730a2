//! The Step Functions developer guide's examples (paths, Parameters, ResultPath, OutputPath,
//! the context object and every intrinsic function), run through the public API.

use lb_asl::{
    AslError, Call, DataFlow, Env, LoadError, Path, RandomSource, ResultPath, Selection, Template,
};
use serde_json::{json, Value};

fn render(template: Value, input: Value) -> Result<Value, AslError> {
    Template::compile(&template)
        .expect("template compiles")
        .render(&input, &Env::none())
}

fn call(text: &str, input: Value) -> Result<Value, AslError> {
    render(json!({ "out.$": text }), input).map(|v| v["out"].clone())
}

fn load_error(text: &str) -> LoadError {
    Call::parse_at(text, "out.$").expect_err(text)
}

// ---- Parameters, InputPath, OutputPath, ResultPath ---------------------------------------

#[test]
fn parameters_select_nested_values_and_keep_static_ones() {
    let input = json!({
        "comment": "Example for Parameters.",
        "product": {
            "details": {"color": "blue", "size": "small", "material": "cotton"},
            "availability": "in stock", "sku": "2317", "cost": "$23"
        }
    });
    let params = json!({
        "comment": "Selecting what I care about.",
        "MyDetails": {
            "size.$": "$.product.details.size",
            "exists.$": "$.product.availability",
            "StaticValue": "foo"
        }
    });
    assert_eq!(
        render(params, input).unwrap(),
        json!({
            "comment": "Selecting what I care about.",
            "MyDetails": {"size": "small", "exists": "in stock", "StaticValue": "foo"}
        })
    );
}

#[test]
fn parameters_render_objects_inside_arrays_and_leave_plain_values_literal() {
    let out = render(
        json!({"list": [{"a.$": "$.x"}, "$.x", 3, null], "n": "$.not-a-path"}),
        json!({"x": [1, 2]}),
    )
    .unwrap();
    assert_eq!(
        out,
        json!({"list": [{"a": [1, 2]}, "$.x", 3, null], "n": "$.not-a-path"})
    );
}

#[test]
fn a_missing_parameter_path_fails_with_the_aws_message_and_states_runtime() {
    let err = render(json!({"JobName.$": "$.JobName"}), json!({})).unwrap_err();
    assert_eq!(err.name(), "States.Runtime");
    assert_eq!(
        err.to_string(),
        "The JSONPath '$.JobName' specified for the field 'JobName.$' could not be found in the input '{}'"
    );
}

#[test]
fn the_context_object_is_read_with_double_dollar() {
    let ctx = json!({"Execution": {"Id": "arn:aws:states:us-east-1:123456789012:execution:m:e"},
                     "Map": {"Item": {"Index": 2, "Value": {"who": "joe"}}}});
    let t = Template::compile(&json!({
        "MessageBody": {"From": "YVR", "Execution.$": "$$.Execution.Id"},
        "ContextIndex.$": "$$.Map.Item.Index",
        "ContextValue.$": "$$.Map.Item.Value"
    }))
    .unwrap();
    let out = t.render(&json!({}), &Env::with_context(&ctx)).unwrap();
    assert_eq!(
        out,
        json!({
            "MessageBody": {"From": "YVR", "Execution": "arn:aws:states:us-east-1:123456789012:execution:m:e"},
            "ContextIndex": 2, "ContextValue": {"who": "joe"}
        })
    );
    let err = t.render(&json!({}), &Env::none()).unwrap_err();
    assert_eq!(err.name(), "States.Runtime");
    assert!(
        err.to_string()
            .contains("could not be found in the input 'null'"),
        "{err}"
    );
}

#[test]
fn input_path_selects_part_of_the_input() {
    let input = json!({
        "comment": "Example for InputPath.",
        "dataset1": {"val1": 1, "val2": 2, "val3": 3},
        "dataset2": {"val1": "a", "val2": "b", "val3": "c"}
    });
    let sel = Selection::from_field(Some(&json!("$.dataset2")), "InputPath").unwrap();
    assert_eq!(
        sel.apply(input).unwrap(),
        json!({"val1": "a", "val2": "b", "val3": "c"})
    );
    let null = Selection::from_field(Some(&Value::Null), "InputPath").unwrap();
    assert_eq!(null.apply(json!({"a": 1})).unwrap(), json!({}));
    let err = Selection::from_field(Some(&json!("$.nope")), "InputPath")
        .unwrap()
        .apply(json!({"a": 1}))
        .unwrap_err();
    assert_eq!(err.name(), "States.Runtime");
    assert_eq!(
        err.to_string(),
        "Invalid path '$.nope' : No results for path: $['nope']"
    );
}

fn lambda_input() -> Value {
    json!({
        "comment": "This is a test of the input and output of a Task state.",
        "details": "Default example",
        "who": "AWS Step Functions"
    })
}

#[test]
fn result_path_default_and_dollar_replace_the_input() {
    let result = json!("Hello, AWS Step Functions!");
    for field in [None, Some(json!("$"))] {
        let rp = ResultPath::from_field(field.as_ref()).unwrap();
        assert_eq!(rp.apply(lambda_input(), result.clone()).unwrap(), result);
    }
}

#[test]
fn result_path_null_discards_the_result_and_keeps_the_input() {
    let rp = ResultPath::from_field(Some(&Value::Null)).unwrap();
    assert_eq!(
        rp.apply(lambda_input(), json!("Hello, AWS Step Functions!"))
            .unwrap(),
        lambda_input()
    );
}

#[test]
fn result_path_includes_the_result_with_the_input() {
    let rp = ResultPath::from_field(Some(&json!("$.taskresult"))).unwrap();
    let mut expected = lambda_input();
    expected["taskresult"] = json!("Hello, AWS Step Functions!");
    assert_eq!(
        rp.apply(lambda_input(), json!("Hello, AWS Step Functions!"))
            .unwrap(),
        expected
    );

    let input = json!({"comment": "An input comment.",
        "strings": {"string1": "foo", "string2": "bar", "string3": "baz"},
        "who": "AWS Step Functions"});
    let rp = ResultPath::from_field(Some(&json!("$.strings.lambdaresult"))).unwrap();
    assert_eq!(
        rp.apply(input, json!("Hello, AWS Step Functions!"))
            .unwrap(),
        json!({"comment": "An input comment.",
            "strings": {"string1": "foo", "string2": "bar", "string3": "baz",
                        "lambdaresult": "Hello, AWS Step Functions!"},
            "who": "AWS Step Functions"})
    );
}

#[test]
fn result_path_updates_an_existing_node() {
    let rp = ResultPath::from_field(Some(&json!("$.comment"))).unwrap();
    let mut expected = lambda_input();
    expected["comment"] = json!("Hello, AWS Step Functions!");
    assert_eq!(
        rp.apply(lambda_input(), json!("Hello, AWS Step Functions!"))
            .unwrap(),
        expected
    );
}

#[test]
fn result_path_in_a_catch_keeps_the_error_beside_the_input() {
    let rp = ResultPath::from_field(Some(&json!("$.error"))).unwrap();
    assert_eq!(
        rp.apply(json!({"foo": "bar"}), json!({"Error": "Error here"}))
            .unwrap(),
        json!({"foo": "bar", "error": {"Error": "Error here"}})
    );
}

#[test]
fn result_path_into_a_non_object_is_a_result_path_match_failure() {
    let rp = ResultPath::from_field(Some(&json!("$.a.b"))).unwrap();
    let err = rp.apply(json!({"a": 3}), json!(1)).unwrap_err();
    assert_eq!(err.name(), "States.ResultPathMatchFailure");
    assert!(err
        .to_string()
        .starts_with("Unable to apply ResultPath '$.a.b' to input '{\"a\":3}'"));
}

#[test]
fn result_path_must_be_a_reference_path_into_the_input() {
    for bad in [
        json!("$.a[*]"),
        json!("$..a"),
        json!("$$.Execution"),
        json!(3),
    ] {
        let err = ResultPath::from_field(Some(&bad)).unwrap_err();
        assert_eq!(err.name(), "InvalidReferencePath", "{bad}");
    }
}

#[test]
fn the_guide_s_input_result_and_output_path_example_adds_then_selects_the_sum() {
    let state = json!({"InputPath": "$.numbers", "ResultPath": "$.sum", "OutputPath": "$"});
    let flow = DataFlow::from_state(state.as_object().unwrap()).unwrap();
    let raw = json!({"title": "Numbers to add", "numbers": {"val1": 3, "val2": 4}});
    assert_eq!(
        flow.effective_input(&raw, &Env::none()).unwrap(),
        json!({"val1": 3, "val2": 4})
    );
    assert_eq!(
        flow.output(raw.clone(), json!(7), &Env::none()).unwrap(),
        json!({"title": "Numbers to add", "numbers": {"val1": 3, "val2": 4}, "sum": 7})
    );
    let state = json!({"InputPath": "$.numbers", "ResultPath": "$.sum", "OutputPath": "$.sum"});
    let flow = DataFlow::from_state(state.as_object().unwrap()).unwrap();
    assert_eq!(flow.output(raw, json!(7), &Env::none()).unwrap(), json!(7));
}

#[test]
fn result_selector_reshapes_the_result_before_result_path() {
    let state = json!({
        "ResultSelector": {"ClusterId.$": "$.output.ClusterId", "ResourceType.$": "$.resourceType"},
        "ResultPath": "$.EMROutput"
    });
    let flow = DataFlow::from_state(state.as_object().unwrap()).unwrap();
    let result = json!({"resourceType": "elasticmapreduce", "resource": "createCluster.sync",
                        "output": {"SdkHttpMetadata": {}, "ClusterId": "AKIAIOSFODNN7EXAMPLE"}});
    assert_eq!(
        flow.output(json!({"x": 1}), result, &Env::none()).unwrap(),
        json!({"x": 1, "EMROutput": {"ClusterId": "AKIAIOSFODNN7EXAMPLE", "ResourceType": "elasticmapreduce"}})
    );
}

#[test]
fn output_path_null_sends_an_empty_object() {
    let state = json!({"OutputPath": null});
    let flow = DataFlow::from_state(state.as_object().unwrap()).unwrap();
    assert_eq!(
        flow.output(json!({"a": 1}), json!(2), &Env::none())
            .unwrap(),
        json!({})
    );
}

// ---- Payload template load errors --------------------------------------------------------

#[test]
fn payload_templates_with_bad_dynamic_fields_are_refused_at_load_time() {
    for (template, name, needle) in [
        (
            json!({"a.$": 3}),
            "InvalidPayloadTemplate",
            "must be a string",
        ),
        (
            json!({"a.$": "plain"}),
            "InvalidPayloadTemplate",
            "neither a JSONPath",
        ),
        (
            json!({"a": 1, "a.$": "$.x"}),
            "InvalidPayloadTemplate",
            "defined twice",
        ),
        (
            json!({".$": "$.x"}),
            "InvalidPayloadTemplate",
            "cannot be empty",
        ),
        (
            json!({"x": {"y": [{"b.$": "$.["}]}}),
            "InvalidJsonPath",
            "x.y[0].b.$",
        ),
        (
            json!({"c.$": "States.Nope()"}),
            "InvalidIntrinsicFunction",
            "unknown function",
        ),
    ] {
        let err = Template::compile(&template).expect_err(&template.to_string());
        assert_eq!(err.name(), name, "{template}");
        assert!(err.to_string().contains(needle), "{template}: {err}");
    }
}

#[test]
fn a_template_lists_every_path_it_reads() {
    let t = Template::compile(&json!({
        "a.$": "$.x",
        "b": [{"c.$": "States.Format('{}-{}', $.y, States.Array($$.z))"}],
        "d": "literal"
    }))
    .unwrap();
    let fields: Vec<(String, Vec<String>)> = t
        .dynamic_fields()
        .into_iter()
        .map(|f| {
            (
                f.location,
                f.paths.iter().map(|p| p.text().to_owned()).collect(),
            )
        })
        .collect();
    assert_eq!(
        fields,
        vec![
            ("a.$".to_owned(), vec!["$.x".to_owned()]),
            (
                "b[0].c.$".to_owned(),
                vec!["$.y".to_owned(), "$$.z".to_owned()]
            ),
        ]
    );
    assert!(Template::compile(&json!({"a": [1]})).unwrap().is_literal());
}

// ---- Intrinsic functions: each documented example ----------------------------------------

#[test]
fn format_interpolates_literal_and_path_templates() {
    let input = json!({"name": "Arnav", "template": "Hello, my name is {}."});
    assert_eq!(
        call(
            "States.Format('Hello, my name is {}.', $.name)",
            input.clone()
        )
        .unwrap(),
        json!("Hello, my name is Arnav.")
    );
    assert_eq!(
        call("States.Format($.template, $.name)", input).unwrap(),
        json!("Hello, my name is Arnav.")
    );
}

#[test]
fn format_writes_non_strings_as_step_functions_does() {
    let input = json!({"n": 1, "f": 1.1, "z": null, "b": true, "o": {"Arg1": 1, "Arg2": []}, "l": ["x", 2]});
    assert_eq!(
        call(
            "States.Format('{} {} {} {} {} {}', $.n, $.f, $.z, $.b, $.o, $.l)",
            input
        )
        .unwrap(),
        json!("1 1.1 null true {Arg1=1, Arg2=[]} [x, 2]")
    );
}

#[test]
fn format_escapes_reserved_characters() {
    // In JSON these read \\' \\{ \\} and \\\\; the call text holds one backslash each.
    let out = call(
        r"States.Format('It\'s \{literal\} and {} with a \\ backslash', $.v)",
        json!({"v": "value"}),
    )
    .unwrap();
    assert_eq!(out, json!(r"It's {literal} and value with a \ backslash"));
}

#[test]
fn format_refuses_a_wrong_count_open_escapes_and_lone_braces_at_load() {
    for (text, needle) in [
        ("States.Format('{} {}', $.a)", "2 `{}` but 1 value"),
        ("States.Format('x', $.a)", "0 `{}` but 1 value"),
        (r"States.Format('a \n b')", "open escape backslash"),
        ("States.Format('a { b')", "unescaped `{`"),
        ("States.Format('a } b')", "unescaped `}`"),
        ("States.Format(3)", "must be a string"),
        ("States.Format()", "at least 1 argument"),
    ] {
        let err = load_error(text);
        assert_eq!(err.name(), "InvalidIntrinsicFunction");
        assert!(err.to_string().contains(needle), "{text}: {err}");
    }
    let err = call("States.Format($.t, $.a)", json!({"t": "{} {}", "a": 1})).unwrap_err();
    assert_eq!(err.name(), "States.IntrinsicFailure");
    assert!(err.to_string().contains("2 `{}` but 1 value"), "{err}");
}

#[test]
fn string_to_json_parses_an_escaped_json_string() {
    assert_eq!(
        call(
            "States.StringToJson($.escapedJsonString)",
            json!({"escapedJsonString": "{\"foo\": \"bar\"}"})
        )
        .unwrap(),
        json!({"foo": "bar"})
    );
    let err = call("States.StringToJson($.s)", json!({"s": "{nope"})).unwrap_err();
    assert_eq!(err.name(), "States.IntrinsicFailure");
}

#[test]
fn json_to_string_serializes_the_node_a_path_names() {
    assert_eq!(
        call(
            "States.JsonToString($.unescapedJson)",
            json!({"unescapedJson": {"foo": "bar"}})
        )
        .unwrap(),
        json!("{\"foo\":\"bar\"}")
    );
    assert!(load_error("States.JsonToString('x')")
        .to_string()
        .contains("must be a path"));
}

#[test]
fn array_collects_its_arguments() {
    assert_eq!(
        render(
            json!({"BuildId.$": "States.Array($.Id)"}),
            json!({"Id": 123456})
        )
        .unwrap(),
        json!({"BuildId": [123456]})
    );
    assert_eq!(
        call(
            "States.Array('a', 1, -2.5, true, null, States.Array())",
            json!({})
        )
        .unwrap(),
        json!(["a", 1, -2.5, true, null, []])
    );
}

#[test]
fn array_partition_chunks_with_a_shorter_last_chunk() {
    let input = json!({"inputArray": [1, 2, 3, 4, 5, 6, 7, 8, 9]});
    assert_eq!(
        call("States.ArrayPartition($.inputArray,4)", input.clone()).unwrap(),
        json!([[1, 2, 3, 4], [5, 6, 7, 8], [9]])
    );
    assert_eq!(
        call("States.ArrayPartition($.inputArray, 3.6)", input.clone()).unwrap(),
        json!([[1, 2, 3, 4], [5, 6, 7, 8], [9]])
    );
    assert!(load_error("States.ArrayPartition($.a, 0)")
        .to_string()
        .contains("positive"));
    let err = call("States.ArrayPartition($.n, 2)", json!({"n": 3})).unwrap_err();
    assert!(err.to_string().contains("must be an array"), "{err}");
}

#[test]
fn array_contains_looks_for_a_value() {
    let input = json!({"inputArray": [1, 2, 3, 4, 5, 6, 7, 8, 9], "lookingFor": 5});
    assert_eq!(
        call("States.ArrayContains($.inputArray, $.lookingFor)", input).unwrap(),
        json!(true)
    );
    assert_eq!(
        call(
            "States.ArrayContains($.a, 1.0)",
            json!({"a": [{"x": 1}, 1]})
        )
        .unwrap(),
        json!(true)
    );
    assert_eq!(
        call("States.ArrayContains($.a, 'z')", json!({"a": ["x"]})).unwrap(),
        json!(false)
    );
}

#[test]
fn array_range_counts_by_the_step_up_to_a_thousand_items() {
    assert_eq!(
        render(json!({"array.$": "States.ArrayRange(1, 9, 2)"}), json!({})).unwrap(),
        json!({"array": [1, 3, 5, 7, 9]})
    );
    assert_eq!(
        call("States.ArrayRange(5, 1, -2)", json!({})).unwrap(),
        json!([5, 3, 1])
    );
    assert_eq!(
        call("States.ArrayRange(1, 5, -1)", json!({})).unwrap(),
        json!([])
    );
    assert_eq!(
        call("States.ArrayRange(0, 999, 1)", json!({}))
            .unwrap()
            .as_array()
            .unwrap()
            .len(),
        1000
    );
    let err = call("States.ArrayRange(0, 1000, 1)", json!({})).unwrap_err();
    assert!(err.to_string().contains("1001 items"), "{err}");
    assert!(load_error("States.ArrayRange(1, 2, 0)")
        .to_string()
        .contains("zero"));
    assert!(load_error("States.ArrayRange(1, 2)")
        .to_string()
        .contains("takes 3"));
}

#[test]
fn array_get_item_returns_the_value_at_an_index() {
    let input = json!({"inputArray": [1, 2, 3, 4, 5, 6, 7, 8, 9], "index": 5});
    assert_eq!(
        render(
            json!({"item.$": "States.ArrayGetItem($.inputArray, $.index)"}),
            input.clone()
        )
        .unwrap(),
        json!({"item": 6})
    );
    let err = call("States.ArrayGetItem($.inputArray, 9)", input).unwrap_err();
    assert_eq!(err.name(), "States.IntrinsicFailure");
    assert!(err.to_string().contains("out of bounds"), "{err}");
    assert!(load_error("States.ArrayGetItem($.a, -1)")
        .to_string()
        .contains("negative"));
}

#[test]
fn array_length_counts_items() {
    assert_eq!(
        render(
            json!({"length.$": "States.ArrayLength($.inputArray)"}),
            json!({"inputArray": [1, 2, 3, 4, 5, 6, 7, 8, 9]})
        )
        .unwrap(),
        json!({"length": 9})
    );
}

#[test]
fn array_unique_keeps_first_occurrences() {
    assert_eq!(
        call(
            "States.ArrayUnique($.inputArray)",
            json!({"inputArray": [1, 2, 3, 3, 3, 3, 3, 3, 4]})
        )
        .unwrap(),
        json!([1, 2, 3, 4])
    );
}

#[test]
fn base64_encodes_and_decodes_text() {
    assert_eq!(
        call(
            "States.Base64Encode($.input)",
            json!({"input": "Data to encode"})
        )
        .unwrap(),
        json!("RGF0YSB0byBlbmNvZGU=")
    );
    assert_eq!(
        call(
            "States.Base64Decode($.base64)",
            json!({"base64": "RGF0YSB0byBlbmNvZGU="})
        )
        .unwrap(),
        json!("Data to encode")
    );
    let long = "x".repeat(10_001);
    let err = call("States.Base64Encode($.s)", json!({ "s": long })).unwrap_err();
    assert!(err.to_string().contains("10000"), "{err}");
    let err = call("States.Base64Decode('%%%')", json!({})).unwrap_err();
    assert!(err.to_string().contains("not valid base64"), "{err}");
}

#[test]
fn hash_computes_every_documented_algorithm() {
    let input = json!({"Data": "input data", "Algorithm": "SHA-1"});
    assert_eq!(
        call("States.Hash($.Data, $.Algorithm)", input).unwrap(),
        json!("aaff4a450a104cd177d28d18d74485e8cae074b7")
    );
    for (alg, hex_len) in [
        ("MD5", 32),
        ("SHA-256", 64),
        ("SHA-384", 96),
        ("SHA-512", 128),
    ] {
        let out = call(&format!("States.Hash('abc', '{alg}')"), json!({})).unwrap();
        assert_eq!(out.as_str().unwrap().len(), hex_len, "{alg}");
    }
    assert_eq!(
        call("States.Hash('abc', 'MD5')", json!({})).unwrap(),
        json!("900150983cd24fb0d6963f7d28e17f72")
    );
    assert!(load_error("States.Hash('a', 'SHA-2')")
        .to_string()
        .contains("MD5, SHA-1"));
    let err = call("States.Hash('a', $.alg)", json!({"alg": "CRC32"})).unwrap_err();
    assert!(err.to_string().contains("unknown algorithm"), "{err}");
}

#[test]
fn json_merge_is_shallow_and_the_second_object_wins() {
    let input = json!({
        "json1": {"a": {"a1": 1, "a2": 2}, "b": 2},
        "json2": {"a": {"a3": 1, "a4": 2}, "c": 3}
    });
    assert_eq!(
        render(
            json!({"output.$": "States.JsonMerge($.json1, $.json2, false)"}),
            input
        )
        .unwrap(),
        json!({"output": {"a": {"a3": 1, "a4": 2}, "b": 2, "c": 3}})
    );
    assert!(load_error("States.JsonMerge($.a, $.b, true)")
        .to_string()
        .contains("shallow"));
    let err = call(
        "States.JsonMerge($.a, $.b, false)",
        json!({"a": {}, "b": [1]}),
    )
    .unwrap_err();
    assert!(
        err.to_string().contains("argument 2 must be an object"),
        "{err}"
    );
}

#[test]
fn math_random_stays_in_range_and_a_seed_fixes_it() {
    let input = json!({"start": 1, "end": 999});
    for _ in 0..50 {
        let v = call("States.MathRandom($.start, $.end)", input.clone()).unwrap();
        let v = v.as_i64().unwrap();
        assert!((1..999).contains(&v), "{v}");
    }
    let a = call("States.MathRandom($.start, $.end, 42)", input.clone()).unwrap();
    let b = call("States.MathRandom($.start, $.end, 42)", input.clone()).unwrap();
    assert_eq!(a, b);
    let seeded = RandomSource::seeded(9);
    let t = Template::compile(&json!({"r.$": "States.MathRandom(0, 1000000)"})).unwrap();
    let env = Env::none().random(&seeded);
    let x = t.render(&json!({}), &env).unwrap();
    let again = RandomSource::seeded(9);
    assert_eq!(
        x,
        t.render(&json!({}), &Env::none().random(&again)).unwrap()
    );
    let err = call("States.MathRandom(5, 5)", json!({})).unwrap_err();
    assert!(err.to_string().contains("less than"), "{err}");
}

#[test]
fn math_add_rounds_to_integers_in_the_32_bit_range() {
    assert_eq!(
        render(
            json!({"value1.$": "States.MathAdd($.value1, $.step)"}),
            json!({"value1": 111, "step": -1})
        )
        .unwrap(),
        json!({"value1": 110})
    );
    assert_eq!(
        call("States.MathAdd(1.5, 2.4)", json!({})).unwrap(),
        json!(4)
    );
    assert_eq!(
        call("States.MathAdd(-2.5, 0)", json!({})).unwrap(),
        json!(-2)
    );
    let err = call("States.MathAdd($.a, 1)", json!({"a": 2147483648_i64})).unwrap_err();
    assert!(
        err.to_string().contains("-2147483648 to 2147483647"),
        "{err}"
    );
    assert!(load_error("States.MathAdd('1', 2)")
        .to_string()
        .contains("must be a number"));
}

#[test]
fn string_split_splits_on_any_delimiter_character() {
    assert_eq!(
        call(
            "States.StringSplit($.inputString, $.splitter)",
            json!({"inputString": "1,2,3,4,5", "splitter": ","})
        )
        .unwrap(),
        json!(["1", "2", "3", "4", "5"])
    );
    assert_eq!(
        call(
            "States.StringSplit($.inputString, $.splitter)",
            json!({"inputString": "This.is+a,test=string", "splitter": ".+,="})
        )
        .unwrap(),
        json!(["This", "is", "a", "test", "string"])
    );
}

#[test]
fn uuid_returns_a_version_4_uuid() {
    let v = call("States.UUID()", json!({})).unwrap();
    let s = v.as_str().unwrap();
    assert_eq!(s.len(), 36);
    assert_eq!(&s[14..15], "4");
    assert!(load_error("States.UUID(1)").to_string().contains("takes 0"));
}

#[test]
fn the_guide_s_nine_nested_calls_evaluate_once_its_placeholder_count_is_fixed() {
    // The guide's example has three `{}` for two values, which Step Functions itself refuses;
    // we refuse it at load time and evaluate the corrected call.
    let guide = "States.Format('{}.{}.{}', States.ArrayGetItem(States.StringSplit(States.ArrayGetItem(States.StringSplit($.ImageRecipe.Arn, '/'), 2), '.'), 0), States.ArrayGetItem(States.StringSplit(States.ArrayGetItem(States.StringSplit($.ImageRecipe.Arn, '/'), 2), '.'), 1))";
    assert!(load_error(guide).to_string().contains("3 `{}` but 2 value"));
    let text = "States.Format('{}.{}', States.ArrayGetItem(States.StringSplit(States.ArrayGetItem(States.StringSplit($.ImageRecipe.Arn, '/'), 2), '.'), 0), States.ArrayGetItem(States.StringSplit(States.ArrayGetItem(States.StringSplit($.ImageRecipe.Arn, '/'), 2), '.'), 1))";
    let input = json!({"ImageRecipe": {"Arn": "arn:aws:imagebuilder:us-east-1:123456789012:image-recipe/x/1.2.3"}});
    assert_eq!(call(text, input).unwrap(), json!("1.2"));
}

#[test]
fn nesting_deeper_than_ten_is_refused() {
    let mut text = "States.Array()".to_owned();
    for _ in 0..9 {
        text = format!("States.Array({text})");
    }
    assert!(Call::parse(&text).is_ok());
    let deeper = format!("States.Array({text})");
    assert!(load_error(&deeper).to_string().contains("at most 10"));
}

#[test]
fn a_missing_argument_path_fails_with_states_runtime() {
    let err = call("States.Array($.missing)", json!({"a": 1})).unwrap_err();
    assert_eq!(err.name(), "States.Runtime");
    assert_eq!(
        err.to_string(),
        "The JsonPath argument for the field 'out.$' could not be found in the input '{\"a\":1}'"
    );
}

#[test]
fn malformed_calls_are_refused_with_the_reason() {
    for (text, needle) in [
        ("States.Format('x'", "unclosed `(`"),
        ("States.Format('x) ", "unclosed string"),
        ("States.Array(1 2)", "expected `,` or `)`"),
        ("States.Array(1) extra", "unexpected text after the call"),
        ("States.Array(nope)", "unexpected text"),
        ("States.Array($.a[)", "argument `$.a[)`"),
        ("States.Array(1.2.3)", "not a number"),
        ("States.Array(,)", "unexpected text"),
        ("States.ArrayLength('x')", "must be an array"),
    ] {
        let err = load_error(text);
        assert_eq!(err.name(), "InvalidIntrinsicFunction", "{text}");
        assert!(err.to_string().contains(needle), "{text}: {err}");
    }
}

#[test]
fn path_arguments_may_hold_brackets_commas_and_parentheses_in_quotes() {
    let input = json!({"a,b": {"x)y": 5}});
    assert_eq!(
        call("States.Array($['a,b']['x)y'], 1)", input).unwrap(),
        json!([5, 1])
    );
}

#[test]
fn paths_parse_once_and_select_many_times() {
    let p = Path::parse("$.a[-1]").unwrap();
    for n in 1..5 {
        let arr: Vec<i64> = (0..n).collect();
        assert_eq!(
            p.select(&json!({ "a": arr }), &Value::Null),
            Some(json!(n - 1))
        );
    }
}
