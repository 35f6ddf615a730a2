//! Local mode provisions what `infra/app.yaml` declares, under the settings' names.

use aws_sdk_sqs::types::QueueAttributeName;
use fake_evalai::Fixture;
use local_stack::stack::{submissions_queue, LOCAL_SETTINGS, SETTINGS_SECRET, TOKEN_SECRET};
use local_stack::{EvalAi, Stack};

#[tokio::test]
#[ignore = "needs moto"]
async fn the_tables_queues_buckets_and_secrets_are_the_templates() {
    let (stack, settings) = Stack::provisioned(EvalAi::Fake(Fixture::default()), LOCAL_SETTINGS)
        .await
        .expect("the stack starts and is provisioned");

    let dynamo = aws_sdk_dynamodb::Client::new(&stack.sdk);
    for lb in settings.leaderboards.values() {
        for (table, sort) in [
            (&lb.submissions_table, "submission_id"),
            (&lb.qualifier_table, "track_codename"),
        ] {
            let described = dynamo
                .describe_table()
                .table_name(table)
                .send()
                .await
                .unwrap_or_else(|e| panic!("{table}: {e:?}"));
            let t = described.table().unwrap();
            let keys: Vec<_> = t
                .key_schema()
                .iter()
                .map(|k| {
                    (
                        k.attribute_name().to_string(),
                        k.key_type().as_str().to_string(),
                    )
                })
                .collect();
            assert_eq!(
                keys,
                [
                    ("team_id".into(), "HASH".into()),
                    (sort.to_string(), "RANGE".to_string())
                ],
                "{table}"
            );
            assert!(
                t.attribute_definitions()
                    .iter()
                    .all(|a| a.attribute_type().as_str() == "S"),
                "{table}: keys are strings, as the original's"
            );
        }
        let s3 = lb_aws::s3_client(&stack.sdk);
        s3.head_bucket()
            .bucket(&lb.bucket)
            .send()
            .await
            .expect("bucket");
    }

    let sqs = aws_sdk_sqs::Client::new(&stack.sdk);
    let url = sqs
        .get_queue_url()
        .queue_name(submissions_queue())
        .send()
        .await
        .expect("EvalAI's queue")
        .queue_url
        .unwrap();
    let attributes = sqs
        .get_queue_attributes()
        .queue_url(&url)
        .attribute_names(QueueAttributeName::All)
        .send()
        .await
        .unwrap();
    let attributes = attributes.attributes().unwrap();
    let redrive: serde_json::Value =
        serde_json::from_str(&attributes[&QueueAttributeName::RedrivePolicy]).unwrap();
    assert!(
        redrive["deadLetterTargetArn"]
            .as_str()
            .unwrap()
            .ends_with(&format!("{}-dlq", submissions_queue())),
        "{redrive}"
    );
    assert_eq!(
        redrive["maxReceiveCount"].to_string().trim_matches('"'),
        "5"
    );
    assert_eq!(attributes[&QueueAttributeName::VisibilityTimeout], "300");
    assert_eq!(attributes[&QueueAttributeName::MaximumMessageSize], "16384");
    // As SQS documents MaximumMessageSize: a larger message is refused at the sender.
    let refused = sqs
        .send_message()
        .queue_url(&url)
        .message_body("x".repeat(16385))
        .send()
        .await;
    assert!(refused.is_err(), "a 16 KiB + 1 message was accepted");

    let secrets = aws_sdk_secretsmanager::Client::new(&stack.sdk);
    let settings_text = secrets
        .get_secret_value()
        .secret_id(SETTINGS_SECRET)
        .send()
        .await
        .unwrap();
    assert!(settings_text
        .secret_string()
        .unwrap()
        .contains(&stack.evalai_url));
    let token = secrets
        .get_secret_value()
        .secret_id(TOKEN_SECRET)
        .send()
        .await
        .unwrap();
    assert!(token.secret_string().unwrap().contains(&stack.evalai_token));
}
