//! Pre-processing: the file's text into one Gerber statement per line, each preceded by a
//! marker comment that carries its line number in the original file.
//!
//! `gerber_parser` reads one command per line and panics or fails on some shapes that real
//! files have: several commands on one line (or a whole file on one line), several commands
//! in one `%...%` block (`%FSLAX24Y24*MOIN*%`), a bare `G0`, non-ASCII bytes where it slices
//! the line. This pass splits the text at the `*` and `%` delimiters, checks the characters,
//! translates the deprecated words the parser does not know (`G70`/`G71` units, `G90`/`G91`
//! absolute/incremental, `G55`, `%LN`) and drops plain comments, so that every `G04` comment
//! the parser returns is one of our markers (standard `G04 #@! ...` X2 attribute comments of
//! KiCad 5 are kept: the parser turns them into attributes).
//!
//! It also fixes what the parser would read wrongly or refuse although the specification
//! allows it: a unit stated twice the same way (`%MOIN*%` and `G70`) is kept once, two that
//! disagree are an error naming both lines; every data word goes through our own tokenizer
//! (coordinates a sign and digits: `+` dropped, decimals, exponents and NaN refused; a
//! missing operation code repeated from the previous one); a byte-order mark is dropped.

use super::GerberError;

/// Prefix of the marker comments; plain comments are dropped, so no real comment starts so.
pub(super) const MARKER: &str = "dpsa:";

/// One statement: a word `...*` or an extended block `%...*%` (an aperture macro keeps its
/// primitives on lines of their own, as the parser expects).
#[derive(Debug)]
struct Statement {
    /// 1-based line in the original text where the statement starts.
    line: usize,
    text: String,
}

fn syntax(line: usize, message: impl Into<String>) -> GerberError {
    GerberError::Syntax {
        line,
        message: message.into(),
    }
}

/// Whether a character may appear in a Gerber file at all: printable text, the line breaks,
/// tabs. Anything else (NUL, other control characters) means the file is not Gerber text.
fn is_text(c: char) -> bool {
    !c.is_control() || matches!(c, '\n' | '\r' | '\t')
}

/// Splits a text into statements, one at a time (the whole file is never held as statements).
/// Errors on binary data and on a `%` block left open.
struct Splitter<'a> {
    chars: std::str::Chars<'a>,
    latin1: bool,
    line: usize,
    word: String,
    word_line: usize,
    /// Inside `%...%`: the block's words so far and the line it opened on.
    block: Option<(Vec<(usize, String)>, usize)>,
    /// Statements of a block already split, handed out first.
    pending: std::collections::VecDeque<Statement>,
    warnings: Vec<String>,
    ended: bool,
}

impl<'a> Splitter<'a> {
    fn new(text: &'a str, latin1: bool) -> Splitter<'a> {
        Splitter {
            chars: text.chars(),
            latin1,
            line: 1,
            word: String::new(),
            word_line: 1,
            block: None,
            pending: Default::default(),
            warnings: Vec::new(),
            ended: false,
        }
    }

    /// The next statement, `None` at the end of the text.
    fn next(&mut self) -> Result<Option<Statement>, GerberError> {
        loop {
            if let Some(st) = self.pending.pop_front() {
                return Ok(Some(st));
            }
            if self.ended {
                return Ok(None);
            }
            let Some(c) = self.chars.next() else {
                self.finish()?;
                continue;
            };
            if let Some(st) = self.char(c)? {
                return Ok(Some(st));
            }
        }
    }

    fn char(&mut self, c: char) -> Result<Option<Statement>, GerberError> {
        let line = self.line;
        if !is_text(c) {
            return Err(GerberError::Binary { line });
        }
        if self.latin1 && !c.is_ascii() {
            // Text that is not UTF-8 may have Latin-1 only in comments and attributes.
            let word = &self.word;
            let free = match &self.block {
                Some((words, _)) => {
                    words.first().is_some_and(|(_, w)| w.starts_with("AM"))
                        || ["TF", "TA", "TO", "TD", "IN", "AM"]
                            .iter()
                            .any(|p| word.starts_with(p))
                }
                None => word.starts_with("G04"),
            };
            if !free {
                return Err(GerberError::Binary { line });
            }
        }
        match c {
            '\n' => {
                self.line += 1;
                return Ok(None);
            }
            '\r' | '\t' => return Ok(None),
            _ => {}
        }
        if self.word.is_empty() && c != '%' && c.is_whitespace() {
            // Blanks between statements.
            return Ok(None);
        }
        match c {
            // A comment runs to its `*`: Eagle 9 writes its X2 attributes as
            // `G04 #@! %TF.Part,Single*`, with the attribute's `%` inside the comment.
            '%' if self.block.is_none() && self.word.trim_start().starts_with("G04") => {
                self.word.push(c)
            }
            '%' => {
                let w = std::mem::take(&mut self.word);
                match self.block.take() {
                    None => {
                        if !w.trim().is_empty() {
                            return Err(syntax(
                                self.word_line,
                                format!("{:?} is not terminated by '*'", w.trim()),
                            ));
                        }
                        self.block = Some((Vec::new(), line));
                    }
                    Some((words, start)) => {
                        if !w.trim().is_empty() {
                            return Err(syntax(
                                self.word_line,
                                format!("{:?} is not terminated by '*' before '%'", w.trim()),
                            ));
                        }
                        push_block(&mut self.pending, words, start)?;
                    }
                }
            }
            '*' => {
                let w = std::mem::take(&mut self.word);
                let w = w.trim().to_string();
                match &mut self.block {
                    Some((words, _)) => {
                        // A block's words are held until its `%`: a block that never
                        // closes is refused before it holds the whole file.
                        if words.len() >= MAX_BLOCK_WORDS {
                            return Err(syntax(
                                self.block.as_ref().map_or(line, |b| b.1),
                                format!("a %...% block of more than {MAX_BLOCK_WORDS} words"),
                            ));
                        }
                        words.push((self.word_line, w))
                    }
                    None => {
                        if !w.is_empty() {
                            return Ok(Some(Statement {
                                line: self.word_line,
                                text: w,
                            }));
                        }
                    }
                }
            }
            _ => {
                if self.word.is_empty() {
                    self.word_line = line;
                }
                self.word.push(c);
            }
        }
        Ok(None)
    }

    /// The end of the text: an open block is an error, text after the last `*` a warning.
    fn finish(&mut self) -> Result<(), GerberError> {
        self.ended = true;
        if let Some((words, start)) = self.block.take() {
            let what = words
                .first()
                .map(|(_, w)| w.chars().take(2).collect::<String>())
                .unwrap_or_default();
            return Err(if what == "AM" {
                GerberError::UnterminatedMacro { line: start }
            } else {
                syntax(start, "extended command '%' is never closed")
            });
        }
        if !self.word.trim().is_empty() {
            self.warnings.push(format!(
                "line {}: text after the last statement ignored: {:?}",
                self.word_line,
                self.word.trim().chars().take(40).collect::<String>()
            ));
        }
        Ok(())
    }
}

/// Most words in one `%...%` block (an aperture macro's primitives): far above any real macro.
const MAX_BLOCK_WORDS: usize = 100_000;

/// One `%...%` block: an aperture macro stays one multi-line block; any other block with
/// several words becomes one block per word (`%FSLAX24Y24*MOIN*%`).
fn push_block(
    out: &mut std::collections::VecDeque<Statement>,
    words: Vec<(usize, String)>,
    start: usize,
) -> Result<(), GerberError> {
    let Some((_, first)) = words.first() else {
        return Ok(()); // `%%`: nothing
    };
    if first.starts_with("AM") {
        let n = words.len();
        let mut text = String::new();
        for (i, (_, w)) in words.iter().enumerate() {
            if i == 0 {
                text.push('%');
            }
            text.push_str(w);
            text.push('*');
            if i + 1 == n {
                text.push('%');
            } else {
                text.push('\n');
            }
        }
        out.push_back(Statement { line: start, text });
        return Ok(());
    }
    for (line, w) in words {
        if w.is_empty() {
            continue;
        }
        // Deprecated: layer name (no meaning for the image).
        if w.starts_with("LN") {
            continue;
        }
        // Deprecated input code (RS-274X 1998; Mentor writes `%ICAS*%`): ASCII is what this
        // reader reads; another code (EBCDIC, ISO) is not text it can take.
        if let Some(code) = w.strip_prefix("IC") {
            if code == "AS" {
                continue;
            }
            return Err(syntax(
                line,
                format!("%{w}*%: input code {code:?} is not supported (only ICAS, ASCII)"),
            ));
        }
        out.push_back(Statement {
            line,
            text: format!("%{w}*%"),
        });
    }
    Ok(())
}

/// Whether a statement is one whose text may hold any UTF-8 (comments, attributes).
fn free_text(s: &str) -> bool {
    s.starts_with("G04")
        || s.starts_with("%TF")
        || s.starts_with("%TA")
        || s.starts_with("%TO")
        || s.starts_with("%TD")
        || s.starts_with("%IN")
        || s.starts_with("%AM")
}

/// What the rewriting remembers from one statement to the next.
#[derive(Default)]
struct Rewriter {
    /// The units stated so far (`"MM"` or `"IN"`), the line and the statement that said so.
    units: Option<(&'static str, usize, String)>,
    /// The last operation code (1, 2, 3 for D01, D02, D03): coordinates without one repeat it.
    last_op: Option<u8>,
    /// The text was not UTF-8 and was read as Latin-1: non-ASCII outside comments is binary.
    latin1: bool,
}

impl Rewriter {
    /// A unit statement (`%MOMM*%`, `%MOIN*%`, `G71`, `G70`): the first is kept, a later one
    /// that says the same is dropped (the parser refuses a second one), one that disagrees
    /// is an error naming both lines.
    fn unit(
        &mut self,
        unit: &'static str,
        line: usize,
        said: &str,
    ) -> Result<Option<String>, GerberError> {
        match &self.units {
            None => {
                self.units = Some((unit, line, said.to_string()));
                Ok(Some(format!("%MO{unit}*%")))
            }
            Some((u, _, _)) if *u == unit => Ok(None),
            Some((_, first_line, first)) => Err(syntax(
                line,
                format!("{said:?} sets units that disagree with {first:?} on line {first_line}"),
            )),
        }
    }

    /// A data word: an aperture selection (`D10`), a bare operation (`D03`) or coordinates
    /// with an optional operation (`X+100Y-20D01`). Coordinates must be a sign and digits
    /// (the specification allows nothing else: no decimal point, exponent or NaN); a `+`
    /// is dropped (the parser does not take it) and a missing operation code is the previous
    /// one (deprecated modal operation of old generators).
    fn data_word(&mut self, line: usize, w: &str) -> Result<String, GerberError> {
        let bad = |why: String| syntax(line, format!("{w:?}: {why}"));
        if let Some(code) = w.strip_prefix('D') {
            if code.is_empty() || !code.bytes().all(|b| b.is_ascii_digit()) {
                return Err(bad("a D code is digits".into()));
            }
            let n: u32 = code
                .parse()
                .map_err(|_| bad("D code out of range".into()))?;
            return match n {
                1..=3 => {
                    self.last_op = Some(n as u8);
                    Ok(format!("D0{n}"))
                }
                10.. => Ok(w.to_string()),
                _ => Err(bad(format!("unknown operation D{n}"))),
            };
        }
        let mut out = String::with_capacity(w.len() + 3);
        let mut seen = String::new();
        let mut op = None;
        let mut rest = w;
        while let Some(letter) = rest.chars().next() {
            let value_len = rest[1..]
                .find(|c: char| c.is_ascii_uppercase() && "XYIJD".contains(c))
                .unwrap_or(rest.len() - 1);
            let value = &rest[1..1 + value_len];
            rest = &rest[1 + value_len..];
            if op.is_some() {
                return Err(bad("the operation code must come last".into()));
            }
            match letter {
                'X' | 'Y' | 'I' | 'J' => {
                    if seen.contains(letter) {
                        return Err(bad(format!("{letter} given twice")));
                    }
                    seen.push(letter);
                    let digits = value.strip_prefix(['+', '-']).unwrap_or(value);
                    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
                        return Err(bad(format!(
                            "coordinate {letter}{value:?} is not an integer of the %FS format \
                             (only a sign and digits are allowed: no decimal point, exponent \
                             or NaN)"
                        )));
                    }
                    out.push(letter);
                    out.push_str(value.strip_prefix('+').unwrap_or(value));
                }
                'D' => {
                    let n: u32 = value
                        .parse()
                        .ok()
                        .filter(|n| {
                            (1..=3).contains(n) && value.bytes().all(|b| b.is_ascii_digit())
                        })
                        .ok_or_else(|| {
                            bad(format!("D{value} is not an operation (D01, D02, D03)"))
                        })?;
                    op = Some(n as u8);
                }
                c => return Err(bad(format!("unexpected {c:?} in a coordinate word"))),
            }
        }
        let op = match op.or(self.last_op) {
            Some(op) => op,
            None => {
                return Err(bad(
                    "coordinates without an operation code (D01, D02, D03) and no earlier one \
                     to repeat"
                        .into(),
                ))
            }
        };
        self.last_op = Some(op);
        out.push_str(&format!("D0{op}"));
        Ok(out)
    }

    /// Rewrites one statement for the parser: `None` drops it, an error refuses it.
    fn rewrite(&mut self, st: &Statement) -> Result<Option<String>, GerberError> {
        let s = st.text.as_str();
        if !free_text(s) && !s.is_ascii() {
            if self.latin1 {
                return Err(GerberError::Binary { line: st.line });
            }
            return Err(syntax(
                st.line,
                format!(
                    "unexpected character in {:?}",
                    s.chars().take(40).collect::<String>()
                ),
            ));
        }
        if let Some(comment) = s.strip_prefix("G04") {
            // Standard comments (`#@!`) carry X2 attributes (KiCad 5); others are dropped.
            // Eagle 9 writes them with a leading `%` (`G04 #@! %TF...`): the parser takes
            // the KiCad form, without it.
            return match comment.trim_start().strip_prefix("#@!") {
                Some(attr) => {
                    let attr = attr.trim_start().trim_start_matches('%');
                    check_pin_attribute(st.line, attr)?;
                    Ok(Some(format!("G04 #@! {attr}")))
                }
                None => Ok(None),
            };
        }
        if let Some(u) = s.strip_prefix("%MO").and_then(|u| u.strip_suffix("*%")) {
            return match u {
                "MM" => self.unit("MM", st.line, s),
                "IN" => self.unit("IN", st.line, s),
                _ => Err(syntax(st.line, format!("unknown units {s:?}"))),
            };
        }
        if s.starts_with(['X', 'Y', 'I', 'J', 'D']) {
            return self.data_word(st.line, s).map(Some);
        }
        if let Some(after_g) = s.strip_prefix('G') {
            // The parser slices the 3 characters after 'G'; a shorter word would panic it.
            let digits: String = after_g.chars().take_while(|c| c.is_ascii_digit()).collect();
            let rest = &after_g[digits.len()..];
            let code: u32 = digits
                .parse()
                .map_err(|_| syntax(st.line, format!("unknown command {s:?}")))?;
            let rest = if rest.is_empty() {
                String::new()
            } else {
                self.data_word(st.line, rest)?
            };
            let with_rest = |word: &str| -> String {
                if rest.is_empty() {
                    word.to_string()
                } else {
                    format!("{word}\n{rest}")
                }
            };
            let unit = |me: &mut Self, unit: &'static str| -> Result<String, GerberError> {
                let word = me.unit(unit, st.line, s)?;
                Ok(match (word, rest.is_empty()) {
                    (Some(w), _) => with_rest(&w),
                    (None, true) => String::new(),
                    (None, false) => rest.clone(),
                })
            };
            let out = match code {
                1 => with_rest("G01"),
                2 => with_rest("G02"),
                3 => with_rest("G03"),
                36 => with_rest("G36"),
                37 => with_rest("G37"),
                54 => with_rest("G54"),
                // G55: "prepare for flash", deprecated, no effect.
                55 => rest.clone(),
                // Units (deprecated words).
                70 => unit(self, "IN")?,
                71 => unit(self, "MM")?,
                74 => with_rest("G74"),
                75 => with_rest("G75"),
                // Absolute / incremental notation (deprecated): told by marker.
                90 => with_rest(&format!("G04 {MARKER}notation:absolute")),
                91 => with_rest(&format!("G04 {MARKER}notation:incremental")),
                _ => return Err(syntax(st.line, format!("unknown command {s:?}"))),
            };
            return Ok(if out.is_empty() { None } else { Some(out) });
        }
        check_transform(st.line, s)?;
        if let Some(attr) = s.strip_prefix('%') {
            check_pin_attribute(st.line, attr)?;
        }
        Ok(Some(s.to_string()))
    }
}

/// A pin attribute (`TO.P,<refdes>,<pin>[,<function>]`) with fewer than two values: the parser
/// crate indexes its second value without looking (a panic, found by the `load_gerber` fuzz
/// target), and such an attribute names no pin anyway.
fn check_pin_attribute(line: usize, attr: &str) -> Result<(), GerberError> {
    let Some(body) = attr.strip_prefix("TO") else {
        return Ok(());
    };
    let body = body.trim_end_matches(['*', '%']);
    let mut fields = body.split(',');
    if fields.next().map(str::trim) != Some(".P") || fields.count() >= 2 {
        return Ok(());
    }
    Err(syntax(
        line,
        format!(
            "%TO{body}*%: a pin attribute takes a reference designator and a pin number \
             (%TO.P,U3,14*%)"
        ),
    ))
}

/// The load-transform commands (`%LP`, `%LM`, `%LR`, `%LS`) checked here, so that a bad
/// value is reported with its own command's syntax (the parser's message quotes the `%LM`
/// pattern for any of them).
fn check_transform(line: usize, s: &str) -> Result<(), GerberError> {
    let Some(body) = s.strip_prefix("%L").and_then(|b| b.strip_suffix("*%")) else {
        return Ok(());
    };
    let (cmd, value) = body.split_at(body.len().min(1));
    let decimal = |v: &str| -> Option<f64> {
        let ok = !v.is_empty()
            && v.chars()
                .all(|c| c.is_ascii_digit() || matches!(c, '.' | '+' | '-'));
        ok.then(|| v.parse::<f64>().ok())
            .flatten()
            .filter(|x| x.is_finite())
    };
    match cmd {
        "P" if !matches!(value, "C" | "D") => Err(syntax(
            line,
            format!("%LP (load polarity) takes C or D, found {value:?} in {s:?}"),
        )),
        "M" if !matches!(value, "N" | "X" | "Y" | "XY") => Err(syntax(
            line,
            format!("%LM (load mirroring) takes N, X, Y or XY, found {value:?} in {s:?}"),
        )),
        "R" if decimal(value).is_none() => Err(syntax(
            line,
            format!(
                "%LR (load rotation) takes a decimal angle in degrees (e.g. %LR45.0*%), found {value:?} in {s:?}"
            ),
        )),
        "S" if decimal(value).is_none_or(|x| x <= 0.0) => Err(syntax(
            line,
            format!(
                "%LS (load scaling) takes a decimal scale factor above 0 (e.g. %LS0.8*%), found {value:?} in {s:?}"
            ),
        )),
        _ => Ok(()),
    }
}

/// The pre-processing of one text, a chunk of statements at a time: the parser and the
/// interpreter never hold more than one chunk's commands, whatever the size of the file.
pub(super) struct Lexer<'a> {
    split: Splitter<'a>,
    rw: Rewriter,
    /// The first `%FS` statement: repeated at the head of every later chunk (the parser
    /// needs it for coordinates), with the units.
    format: Option<String>,
    /// Chunks handed out so far.
    chunks: usize,
    latin1_warned: bool,
}

/// One chunk of the pre-processed text.
#[derive(Debug)]
pub(super) struct Lexed {
    /// Statements, one per line, each after a `G04 dpsa:line:N*` marker.
    pub text: String,
    /// Original line of every line of `text` (index 0 = line 1 of `text`).
    pub line_map: Vec<usize>,
    /// The first `prelude` lines repeat the format and units of earlier chunks: the parser's
    /// commands for them are not the file's.
    pub prelude: usize,
    /// What the pre-processing noticed (non-UTF-8 text, text after the last statement).
    pub warnings: Vec<String>,
}

impl Lexed {
    /// The original line of a line of the pre-processed text (1-based in, 1-based out).
    pub fn original_line(&self, pre_line: usize) -> usize {
        pre_line
            .checked_sub(1)
            .and_then(|i| self.line_map.get(i))
            .copied()
            .unwrap_or(0)
    }
}

impl<'a> Lexer<'a> {
    /// A lexer of a text; `latin1`: the file was not UTF-8 and was decoded as Latin-1, so
    /// non-ASCII characters are allowed only in comments and attributes (else binary data).
    pub fn new(text: &'a str, latin1: bool) -> Lexer<'a> {
        // A UTF-8 byte-order mark (some Windows exporters) is not part of the text.
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        Lexer {
            split: Splitter::new(text, latin1),
            rw: Rewriter {
                latin1,
                ..Rewriter::default()
            },
            format: None,
            chunks: 0,
            latin1_warned: false,
        }
    }

    /// The next chunk of at most `statements` statements (`None` after the last). Errors on
    /// binary data, an unterminated `%` block (an aperture macro or another extended
    /// command) and statements the parser cannot be given safely.
    pub fn next_chunk(&mut self, statements: usize) -> Result<Option<Lexed>, GerberError> {
        let mut out = String::new();
        let mut line_map = Vec::new();
        let mut prelude = 0;
        if self.chunks > 0 {
            let units = self.rw.units.as_ref().map(|u| format!("%MO{}*%", u.0));
            for head in [self.format.clone(), units].into_iter().flatten() {
                out.push_str(&head);
                out.push('\n');
                line_map.push(self.split.line);
                prelude += 1;
            }
        }
        let mut warnings = Vec::new();
        if self.rw.latin1 && !self.latin1_warned {
            self.latin1_warned = true;
            warnings.push(
                "the file is not UTF-8: read as Latin-1 (non-ASCII characters only in comments)"
                    .into(),
            );
        }
        let mut taken = 0;
        while taken < statements {
            let Some(st) = self.split.next()? else {
                break;
            };
            taken += 1;
            let Some(body) = self.rw.rewrite(&st)? else {
                continue;
            };
            if self.format.is_none() && body.starts_with("%FS") {
                self.format = Some(body.clone());
            }
            out.push_str(&format!("G04 {MARKER}line:{}*\n", st.line));
            line_map.push(st.line);
            // Words lost their '*' in splitting; the parser wants it back (extended blocks
            // and macro lines end in '*' or '%' already).
            for w in body.split('\n') {
                out.push_str(w);
                if !(w.ends_with('*') || w.ends_with('%')) {
                    out.push('*');
                }
                out.push('\n');
                line_map.push(st.line);
            }
        }
        warnings.append(&mut self.split.warnings);
        if taken == 0 && self.chunks > 0 {
            return Ok(None);
        }
        self.chunks += 1;
        Ok(Some(Lexed {
            text: out,
            line_map,
            prelude,
            warnings,
        }))
    }
}

/// Pre-processes a whole text as one chunk (tests).
#[cfg(test)]
pub(super) fn lex(text: &str) -> Result<Lexed, GerberError> {
    Lexer::new(text, false)
        .next_chunk(usize::MAX)
        .map(|c| c.expect("the first chunk"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lines(text: &str) -> Vec<String> {
        lex(text)
            .expect("lexes")
            .text
            .lines()
            .filter(|l| !l.starts_with("G04 dpsa:line"))
            .map(str::to_string)
            .collect()
    }

    #[test]
    fn splits_one_line_files_and_multi_word_blocks() {
        assert_eq!(
            lines("%FSLAX24Y24*MOIN*%%ADD10C,0.01*%D10*X1Y1D03*X2Y2D03*M02*"),
            [
                "%FSLAX24Y24*%",
                "%MOIN*%",
                "%ADD10C,0.01*%",
                "D10*",
                "X1Y1D03*",
                "X2Y2D03*",
                "M02*"
            ]
        );
    }

    #[test]
    fn keeps_macros_whole_and_maps_lines() {
        let l = lex("%FSLAX26Y26*%\n%MOMM*%\n%AMBOX*\n21,1,$1,$2,0,0,0*%\nG04 hello*\nM02*\n")
            .expect("lexes");
        let text: Vec<&str> = l.text.lines().collect();
        let am = text
            .iter()
            .position(|t| t.starts_with("%AMBOX"))
            .expect("macro");
        assert_eq!(text[am + 1], "21,1,$1,$2,0,0,0*%");
        assert_eq!(l.original_line(am + 1), 3);
        // Plain comments are dropped.
        assert!(!l.text.contains("hello"));
    }

    #[test]
    fn refuses_binary_and_open_blocks() {
        assert!(matches!(
            lex("%FSLAX26Y26*%\n\u{0}\u{1}"),
            Err(GerberError::Binary { line: 2 })
        ));
        assert!(matches!(
            lex("%FSLAX26Y26*%\n%AMFOO*\n1,1,1,0,0*\n"),
            Err(GerberError::UnterminatedMacro { line: 2 })
        ));
        assert!(matches!(lex("G0*"), Err(GerberError::Syntax { .. })));
        assert!(matches!(lex("G9*"), Err(GerberError::Syntax { .. })));
        assert!(matches!(lex("G*"), Err(GerberError::Syntax { .. })));
        assert!(matches!(lex("X1é*"), Err(GerberError::Syntax { .. })));
    }

    #[test]
    fn translates_deprecated_words() {
        assert_eq!(
            lines("G70*G91*G54D10*G01X1Y2D01*G55*"),
            [
                "%MOIN*%",
                "G04 dpsa:notation:incremental*",
                "G54*",
                "D10*",
                "G01*",
                "X1Y2D01*"
            ]
        );
    }
}
