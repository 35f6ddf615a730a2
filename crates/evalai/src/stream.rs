//! A JSON list read element by element as its bytes arrive, each element bounded: EvalAI's
//! submission lists carry what participants wrote (their metadata, their method's
//! description), so one team's large elements must not make the whole list unreadable for
//! everybody else. An element above the bound is skipped and counted, never held.

/// One element of the list, or the place of one that was too large.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Piece {
    /// An element's bytes (JSON, not yet parsed).
    Element(Vec<u8>),
    /// An element of more than the bound: its index and size.
    Oversized {
        /// Its place in the list, from 0.
        index: usize,
        /// Its size in bytes.
        bytes: usize,
    },
}

/// Where the reader is in the list.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum At {
    /// Before the `[`.
    Start,
    /// Between elements.
    Between,
    /// Inside an element.
    Element,
    /// After the `]`.
    End,
}

/// Splits a JSON list into its top-level elements, fed in chunks of any size.
#[derive(Debug)]
pub struct ListSplitter {
    max: usize,
    at: At,
    depth: u32,
    in_string: bool,
    escaped: bool,
    buf: Vec<u8>,
    size: usize,
    index: usize,
}

impl ListSplitter {
    /// A splitter keeping elements of at most `max` bytes.
    pub fn new(max: usize) -> ListSplitter {
        ListSplitter {
            max,
            at: At::Start,
            depth: 0,
            in_string: false,
            escaped: false,
            buf: Vec::new(),
            size: 0,
            index: 0,
        }
    }

    /// Reads `chunk`, adding the elements it completes to `out`; an error names what is not a
    /// JSON list.
    pub fn feed(&mut self, chunk: &[u8], out: &mut Vec<Piece>) -> Result<(), String> {
        for &b in chunk {
            match self.at {
                At::Start if b.is_ascii_whitespace() => {}
                At::Start if b == b'[' => self.at = At::Between,
                At::Start => return Err("the body is not a JSON list".into()),
                At::End if b.is_ascii_whitespace() => {}
                At::End => return Err("bytes after the end of the list".into()),
                At::Between if b.is_ascii_whitespace() || b == b',' => {}
                At::Between if b == b']' => self.at = At::End,
                At::Between => {
                    self.at = At::Element;
                    self.byte(b, out);
                }
                At::Element => self.byte(b, out),
            }
        }
        Ok(())
    }

    /// The end of the body: an error when the list was not closed.
    pub fn finish(&self) -> Result<(), String> {
        match self.at {
            At::End => Ok(()),
            _ => Err("the list ends before its `]`".into()),
        }
    }

    fn byte(&mut self, b: u8, out: &mut Vec<Piece>) {
        if !self.in_string && self.depth == 0 && (b == b',' || b == b']') {
            self.complete(out);
            self.at = if b == b']' { At::End } else { At::Between };
            return;
        }
        if self.in_string {
            match (self.escaped, b) {
                (true, _) => self.escaped = false,
                (false, b'\\') => self.escaped = true,
                (false, b'"') => self.in_string = false,
                _ => {}
            }
        } else {
            match b {
                b'"' => self.in_string = true,
                b'{' | b'[' => self.depth += 1,
                b'}' | b']' => self.depth = self.depth.saturating_sub(1),
                _ => {}
            }
        }
        self.size += 1;
        if self.size <= self.max {
            self.buf.push(b);
        } else if !self.buf.is_empty() {
            // NB: the element's bytes so far are dropped at once; only its size is kept.
            self.buf = Vec::new();
        }
    }

    fn complete(&mut self, out: &mut Vec<Piece>) {
        let piece = if self.size <= self.max {
            Piece::Element(std::mem::take(&mut self.buf))
        } else {
            Piece::Oversized {
                index: self.index,
                bytes: self.size,
            }
        };
        out.push(piece);
        self.index += 1;
        self.size = 0;
        self.depth = 0;
        self.in_string = false;
        self.escaped = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn split(body: &[u8], max: usize, chunk: usize) -> Result<Vec<Piece>, String> {
        let mut splitter = ListSplitter::new(max);
        let mut out = Vec::new();
        for part in body.chunks(chunk.max(1)) {
            splitter.feed(part, &mut out)?;
        }
        splitter.finish()?;
        Ok(out)
    }

    fn element(text: &str) -> Piece {
        Piece::Element(text.as_bytes().to_vec())
    }

    #[test]
    fn elements_come_whole_whatever_the_chunks_and_large_ones_are_only_counted() {
        let big = format!(r#"{{"id": 2, "meta": "{}"}}"#, "x".repeat(100));
        let body = format!(r#" [ {{"id": 1, "s": "a ] , {{ \" }}"}}, {big} ,[1,[2]], "t,]", 3 ] "#);
        for chunk in [1, 2, 7, 1000] {
            let pieces = split(body.as_bytes(), 40, chunk).unwrap();
            assert_eq!(
                pieces,
                [
                    element(r#"{"id": 1, "s": "a ] , { \" }"}"#),
                    // With the space after it, before the comma.
                    Piece::Oversized {
                        index: 1,
                        bytes: big.len() + 1
                    },
                    element("[1,[2]]"),
                    element(r#""t,]""#),
                    element("3 "),
                ],
                "chunks of {chunk}"
            );
        }
        assert_eq!(split(b"[]", 10, 1).unwrap(), []);
    }

    #[test]
    fn what_is_not_a_whole_list_is_named() {
        for (body, problem) in [
            (&b"{\"results\": []}"[..], "not a JSON list"),
            (b"[{\"id\": 1}", "ends before"),
            (b"[1] 2", "after the end"),
            (b"", "ends before"),
        ] {
            let e = split(body, 100, 3).unwrap_err();
            assert!(e.contains(problem), "{e}");
        }
    }
}
