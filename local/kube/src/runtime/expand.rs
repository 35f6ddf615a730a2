//! Kubernetes `$(VAR)` expansion for `command`, `args` and env values (`$$` escapes `$`).

/// Expands `$(NAME)` with `lookup`; unknown names, unclosed `$(` and a lone `$` stay as written,
/// `$$` becomes `$` (the rules of k8s.io/kubernetes third_party/forked/golang/expansion).
pub fn expand(input: &str, lookup: impl Fn(&str) -> Option<String>) -> String {
    let bytes = input.as_bytes();
    let mut out = String::with_capacity(input.len());
    let mut checkpoint = 0;
    let mut cursor = 0;
    while cursor < bytes.len() {
        if bytes[cursor] == b'$' && cursor + 1 < bytes.len() {
            out.push_str(&input[checkpoint..cursor]);
            let rest = &input[cursor + 1..];
            let advance = match rest.as_bytes()[0] {
                b'$' => {
                    out.push('$');
                    1
                }
                b'(' => match rest[1..].find(')') {
                    Some(end) => {
                        let name = &rest[1..1 + end];
                        match lookup(name) {
                            Some(v) => out.push_str(&v),
                            None => {
                                out.push_str("$(");
                                out.push_str(name);
                                out.push(')');
                            }
                        }
                        end + 2
                    }
                    None => {
                        out.push_str("$(");
                        1
                    }
                },
                _ => {
                    // NB: a `$` not starting an expression is kept with the next character.
                    let ch = rest.chars().next().map_or(1, char::len_utf8);
                    out.push('$');
                    out.push_str(&rest[..ch]);
                    ch
                }
            };
            cursor += advance + 1;
            checkpoint = cursor;
        } else {
            cursor += 1;
        }
    }
    out.push_str(&input[checkpoint.min(input.len())..]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(name: &str) -> Option<String> {
        match name {
            "PORT" => Some("2000".into()),
            "EMPTY" => Some(String::new()),
            _ => None,
        }
    }

    #[test]
    fn variables_expand_and_escapes_and_unknowns_stay() {
        assert_eq!(
            expand("-carla-rpc-port=$(PORT)", env),
            "-carla-rpc-port=2000"
        );
        assert_eq!(expand("$(PORT)$(PORT)", env), "20002000");
        assert_eq!(expand("$$(PORT)", env), "$(PORT)");
        assert_eq!(expand("$$$(PORT)", env), "$2000");
        assert_eq!(expand("$(NOPE)", env), "$(NOPE)");
        assert_eq!(expand("a$(EMPTY)b", env), "ab");
        assert_eq!(expand("${PORT} $PORT", env), "${PORT} $PORT");
        assert_eq!(expand("$(PORT", env), "$(PORT");
        assert_eq!(expand("cost: 5$", env), "cost: 5$");
        assert_eq!(expand("$", env), "$");
        assert_eq!(expand("é$(PORT)é", env), "é2000é");
        assert_eq!(expand("$é", env), "$é");
    }
}
