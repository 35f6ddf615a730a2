//! Step Functions as a test scripts it: every report recorded, each answered as told.

use std::collections::VecDeque;
use std::sync::Mutex;

use lb_aws::tasks::{Callbacks, Reported};
use lb_aws::AwsError;

/// How a report is answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Answer {
    /// The waiting task got it.
    Delivered,
    /// Nobody waits on the token any more.
    Stale,
    /// The API cannot be reached: a failure worth retrying.
    Unreachable,
}

/// Records each report (token and output) and answers the scripted answers first, then the
/// standing one (delivered unless told otherwise).
#[derive(Debug)]
pub struct RecordingCallbacks {
    reports: Mutex<Vec<(String, String, Answer)>>,
    next: Mutex<VecDeque<Answer>>,
    standing: Mutex<Answer>,
}

impl Default for RecordingCallbacks {
    fn default() -> Self {
        RecordingCallbacks {
            reports: Mutex::default(),
            next: Mutex::default(),
            standing: Mutex::new(Answer::Delivered),
        }
    }
}

impl RecordingCallbacks {
    /// The next report (after any already scripted) gets `answer`.
    pub fn answer_next(&self, answer: Answer) {
        self.next.lock().unwrap().push_back(answer);
    }

    /// Every report after the scripted ones gets `answer`.
    pub fn answer_always(&self, answer: Answer) {
        *self.standing.lock().unwrap() = answer;
    }

    /// The tokens of every report, answered however, in order.
    pub fn reported(&self) -> Vec<String> {
        self.reports
            .lock()
            .unwrap()
            .iter()
            .map(|(t, _, _)| t.clone())
            .collect()
    }

    /// The tokens of the reports that were delivered, in order.
    pub fn delivered(&self) -> Vec<String> {
        let reports = self.reports.lock().unwrap();
        reports
            .iter()
            .filter(|(_, _, a)| *a == Answer::Delivered)
            .map(|(t, _, _)| t.clone())
            .collect()
    }

    /// The outputs of every report, in order.
    pub fn outputs(&self) -> Vec<String> {
        self.reports
            .lock()
            .unwrap()
            .iter()
            .map(|(_, o, _)| o.clone())
            .collect()
    }
}

impl Callbacks for RecordingCallbacks {
    async fn succeed(&self, token: &str, output: &str) -> lb_aws::Result<Reported> {
        let scripted = self.next.lock().unwrap().pop_front();
        let answer = scripted.unwrap_or(*self.standing.lock().unwrap());
        self.reports
            .lock()
            .unwrap()
            .push((token.to_string(), output.to_string(), answer));
        match answer {
            Answer::Delivered => Ok(Reported::Delivered),
            Answer::Stale => Ok(Reported::Stale),
            Answer::Unreachable => Err(AwsError::Malformed {
                what: "SendTaskSuccess".into(),
                problem: "the API is unreachable (test)".into(),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn scripted_answers_come_first_then_the_standing_one() {
        let callbacks = RecordingCallbacks::default();
        callbacks.answer_next(Answer::Unreachable);
        callbacks.answer_next(Answer::Stale);
        assert!(callbacks.succeed("a", "{}").await.is_err());
        assert_eq!(callbacks.succeed("b", "{}").await.unwrap(), Reported::Stale);
        assert_eq!(
            callbacks.succeed("c", "{}").await.unwrap(),
            Reported::Delivered
        );
        callbacks.answer_always(Answer::Unreachable);
        assert!(callbacks.succeed("d", "x").await.is_err());
        assert_eq!(callbacks.reported(), ["a", "b", "c", "d"]);
        assert_eq!(callbacks.delivered(), ["c"]);
        assert_eq!(callbacks.outputs(), ["{}", "{}", "{}", "x"]);
    }
}
