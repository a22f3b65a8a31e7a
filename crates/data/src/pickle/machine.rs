//! The pickle stack machine: the opcode table, the object arena and the [`Machine`] that runs it.

use std::collections::HashMap;

use super::arena::{over_budget_message, ByteOrder, Callable, Obj, Res, Val};
use super::tree::TreeBuilder;
use super::value::permute_axes;
use super::{DType, NdArray, PickleError, PyValue};
use super::{BUDGET_BASE, BUDGET_PER_INPUT_BYTE, MAX_PROTOCOL};

mod op {
    pub const MARK: u8 = b'(';
    pub const STOP: u8 = b'.';
    pub const POP: u8 = b'0';
    pub const POP_MARK: u8 = b'1';
    pub const DUP: u8 = b'2';
    pub const BININT: u8 = b'J';
    pub const BININT1: u8 = b'K';
    pub const BININT2: u8 = b'M';
    pub const NONE: u8 = b'N';
    pub const REDUCE: u8 = b'R';
    pub const BINUNICODE: u8 = b'X';
    pub const APPEND: u8 = b'a';
    pub const BUILD: u8 = b'b';
    pub const GLOBAL: u8 = b'c';
    pub const DICT: u8 = b'd';
    pub const EMPTY_DICT: u8 = b'}';
    pub const APPENDS: u8 = b'e';
    pub const BINGET: u8 = b'h';
    pub const LONG_BINGET: u8 = b'j';
    pub const LIST: u8 = b'l';
    pub const EMPTY_LIST: u8 = b']';
    pub const BINPUT: u8 = b'q';
    pub const LONG_BINPUT: u8 = b'r';
    pub const SETITEM: u8 = b's';
    pub const TUPLE: u8 = b't';
    pub const EMPTY_TUPLE: u8 = b')';
    pub const SETITEMS: u8 = b'u';
    pub const BINFLOAT: u8 = b'G';
    pub const PROTO: u8 = 0x80;
    pub const TUPLE1: u8 = 0x85;
    pub const TUPLE2: u8 = 0x86;
    pub const TUPLE3: u8 = 0x87;
    pub const NEWTRUE: u8 = 0x88;
    pub const NEWFALSE: u8 = 0x89;
    pub const LONG1: u8 = 0x8a;
    pub const LONG4: u8 = 0x8b;
    pub const BINBYTES: u8 = b'B';
    pub const SHORT_BINBYTES: u8 = b'C';
    pub const SHORT_BINUNICODE: u8 = 0x8c;
    pub const BINUNICODE8: u8 = 0x8d;
    pub const BINBYTES8: u8 = 0x8e;
    pub const STACK_GLOBAL: u8 = 0x93;
    pub const MEMOIZE: u8 = 0x94;
    pub const FRAME: u8 = 0x95;
    pub const BYTEARRAY8: u8 = 0x96;
}

/// Name of every opcode Python defines (protocols 0 to 5), for error messages; `None` for bytes
/// that are not opcodes at all.
fn opcode_name(code: u8) -> Option<&'static str> {
    Some(match code {
        b'(' => "MARK",
        b'.' => "STOP",
        b'0' => "POP",
        b'1' => "POP_MARK",
        b'2' => "DUP",
        b'F' => "FLOAT",
        b'I' => "INT",
        b'J' => "BININT",
        b'K' => "BININT1",
        b'L' => "LONG",
        b'M' => "BININT2",
        b'N' => "NONE",
        b'P' => "PERSID",
        b'Q' => "BINPERSID",
        b'R' => "REDUCE",
        b'S' => "STRING",
        b'T' => "BINSTRING",
        b'U' => "SHORT_BINSTRING",
        b'V' => "UNICODE",
        b'X' => "BINUNICODE",
        b'a' => "APPEND",
        b'b' => "BUILD",
        b'c' => "GLOBAL",
        b'd' => "DICT",
        b'}' => "EMPTY_DICT",
        b'e' => "APPENDS",
        b'g' => "GET",
        b'h' => "BINGET",
        b'i' => "INST",
        b'j' => "LONG_BINGET",
        b'l' => "LIST",
        b']' => "EMPTY_LIST",
        b'o' => "OBJ",
        b'p' => "PUT",
        b'q' => "BINPUT",
        b'r' => "LONG_BINPUT",
        b's' => "SETITEM",
        b't' => "TUPLE",
        b')' => "EMPTY_TUPLE",
        b'u' => "SETITEMS",
        b'G' => "BINFLOAT",
        0x80 => "PROTO",
        0x81 => "NEWOBJ",
        0x82 => "EXT1",
        0x83 => "EXT2",
        0x84 => "EXT4",
        0x85 => "TUPLE1",
        0x86 => "TUPLE2",
        0x87 => "TUPLE3",
        0x88 => "NEWTRUE",
        0x89 => "NEWFALSE",
        0x8a => "LONG1",
        0x8b => "LONG4",
        b'B' => "BINBYTES",
        b'C' => "SHORT_BINBYTES",
        0x8c => "SHORT_BINUNICODE",
        0x8d => "BINUNICODE8",
        0x8e => "BINBYTES8",
        0x8f => "EMPTY_SET",
        0x90 => "ADDITEMS",
        0x91 => "FROZENSET",
        0x92 => "NEWOBJ_EX",
        0x93 => "STACK_GLOBAL",
        0x94 => "MEMOIZE",
        0x95 => "FRAME",
        0x96 => "BYTEARRAY8",
        0x97 => "NEXT_BUFFER",
        0x98 => "READONLY_BUFFER",
        _ => return None,
    })
}

/// Why a real opcode that this reader does not implement is refused.
fn unsupported_reason(code: u8) -> &'static str {
    match code {
        b'F' | b'I' | b'L' | b'S' | b'V' | b'g' | b'p' => {
            "a protocol 0/1 text opcode; numpy data is read from protocols 2 to 5"
        }
        b'T' | b'U' => "a Python 2 str, whose encoding is unknown",
        b'i' | b'o' | 0x81 | 0x92 => "it constructs arbitrary Python objects",
        0x82..=0x84 => "extension registry codes depend on the writer's Python",
        b'P' | b'Q' => "persistent ids need the writer's resolver",
        0x8f..=0x91 => "sets never occur in numpy data",
        0x97 | 0x98 => "out-of-band buffers are not stored in the file",
        _ => "not needed for numpy data",
    }
}

pub(super) struct Machine<'a> {
    input: &'a [u8],
    pos: usize,
    /// Offset and name of the opcode being executed, for error messages.
    op_at: usize,
    op_name: &'static str,
    stack: Vec<Val>,
    /// Stack lengths at each open MARK. Opcodes may not pop below the innermost mark, as in
    /// Python, where MARK starts a fresh stack.
    marks: Vec<usize>,
    memo: HashMap<u32, Val>,
    objs: Vec<Obj>,
    /// Bytes the reader may still spend on values it creates.
    budget: usize,
}

impl<'a> Machine<'a> {
    pub(super) fn new(input: &'a [u8]) -> Self {
        let budget = input.len().saturating_mul(BUDGET_PER_INPUT_BYTE).saturating_add(BUDGET_BASE);
        Machine {
            input,
            pos: 0,
            op_at: 0,
            op_name: "",
            stack: Vec::new(),
            marks: Vec::new(),
            memo: HashMap::new(),
            objs: Vec::new(),
            budget,
        }
    }

    // --- errors ---------------------------------------------------------------------------------

    fn invalid(&self, message: impl Into<String>) -> PickleError {
        PickleError::Invalid { offset: self.op_at, opcode: self.op_name, message: message.into() }
    }

    fn charge(&mut self, bytes: usize) -> Res<()> {
        match self.budget.checked_sub(bytes) {
            Some(left) => {
                self.budget = left;
                Ok(())
            }
            None => Err(PickleError::Limit {
                offset: self.op_at,
                opcode: self.op_name,
                message: over_budget_message(self.input.len()),
            }),
        }
    }

    // --- reading arguments ----------------------------------------------------------------------

    /// The next `n` bytes; checked against what is left before anything is allocated.
    fn take(&mut self, n: usize, what: impl FnOnce() -> String) -> Res<&'a [u8]> {
        let rest = self.input.get(self.pos..).unwrap_or_default();
        match rest.get(..n) {
            Some(bytes) => {
                self.pos += n;
                Ok(bytes)
            }
            None => Err(PickleError::Truncated {
                offset: self.op_at,
                opcode: self.op_name,
                what: what(),
                available: rest.len(),
            }),
        }
    }

    fn fixed<const N: usize>(&mut self) -> Res<[u8; N]> {
        let bytes = self.take(N, || format!("{N}-byte argument"))?;
        <[u8; N]>::try_from(bytes).map_err(|_| self.invalid("internal: argument size"))
    }

    /// A length-prefixed payload: `len_size` little-endian length bytes, then the data.
    fn payload(&mut self, len_size: usize) -> Res<&'a [u8]> {
        let len_bytes = self.take(len_size, || format!("{len_size}-byte length"))?;
        let mut buf = [0u8; 8];
        for (dst, src) in buf.iter_mut().zip(len_bytes) {
            *dst = *src;
        }
        let n = u64::from_le_bytes(buf);
        // A length that does not fit usize is certainly longer than the input.
        let n_usize = usize::try_from(n).unwrap_or(usize::MAX);
        self.take(n_usize, || format!("length {n}"))
    }

    fn line(&mut self, what: &str) -> Res<&'a str> {
        let rest = self.input.get(self.pos..).unwrap_or_default();
        let Some(end) = rest.iter().position(|&b| b == b'\n') else {
            return Err(PickleError::Truncated {
                offset: self.op_at,
                opcode: self.op_name,
                what: format!("{what} (no newline)"),
                available: rest.len(),
            });
        };
        let bytes = rest.get(..end).unwrap_or_default();
        self.pos += end + 1;
        std::str::from_utf8(bytes).map_err(|_| self.invalid(format!("{what} is not UTF-8")))
    }

    // --- the stack ------------------------------------------------------------------------------

    fn floor(&self) -> usize {
        self.marks.last().copied().unwrap_or(0)
    }

    fn push(&mut self, v: Val) {
        self.stack.push(v);
    }

    fn pop(&mut self) -> Res<Val> {
        if self.stack.len() <= self.floor() {
            return Err(self.invalid("stack underflow"));
        }
        self.stack.pop().ok_or_else(|| self.invalid("stack underflow"))
    }

    fn top(&self) -> Res<Val> {
        if self.stack.len() <= self.floor() {
            return Err(self.invalid("stack underflow"));
        }
        self.stack.last().copied().ok_or_else(|| self.invalid("stack underflow"))
    }

    /// Pops everything above the innermost MARK, and the mark.
    fn pop_mark(&mut self) -> Res<Vec<Val>> {
        let mark = self.marks.pop().ok_or_else(|| self.invalid("no MARK on the stack"))?;
        if mark > self.stack.len() {
            return Err(self.invalid("internal: mark above the stack"));
        }
        Ok(self.stack.split_off(mark))
    }

    fn pop_n(&mut self, n: usize) -> Res<Vec<Val>> {
        let len = self.stack.len();
        if len < self.floor() + n {
            return Err(self.invalid("stack underflow"));
        }
        Ok(self.stack.split_off(len - n))
    }

    fn new_obj(&mut self, obj: Obj) -> Val {
        self.objs.push(obj);
        Val::Obj(self.objs.len() - 1)
    }

    fn obj(&self, v: Val) -> Option<&Obj> {
        match v {
            Val::Obj(id) => self.objs.get(id),
            _ => None,
        }
    }

    /// Python's type name of a stack value, for error messages.
    fn kind(&self, v: Val) -> &'static str {
        match v {
            Val::None => "None",
            Val::Bool(_) => "bool",
            Val::Int(_) => "int",
            Val::Float(_) => "float",
            Val::Obj(_) => match self.obj(v) {
                Some(Obj::Str(_)) => "str",
                Some(Obj::Bytes(_)) => "bytes",
                Some(Obj::List(_)) => "list",
                Some(Obj::Tuple(_)) => "tuple",
                Some(Obj::Dict(_)) => "dict",
                Some(Obj::Callable(_)) => "global",
                Some(Obj::Dtype { .. }) => "numpy.dtype",
                Some(Obj::PendingArray) => "numpy.ndarray (without data)",
                Some(Obj::Array(_)) => "numpy.ndarray",
                None => "?",
            },
        }
    }

    fn str_of(&self, v: Val, what: &str) -> Res<&str> {
        match self.obj(v) {
            Some(Obj::Str(s)) => Ok(s),
            _ => Err(self.invalid(format!("{what} must be a str, got {}", self.kind(v)))),
        }
    }

    fn bytes_of(&self, v: Val, what: &str) -> Res<&[u8]> {
        match self.obj(v) {
            Some(Obj::Bytes(b)) => Ok(b),
            Some(Obj::List(_)) => {
                Err(self.invalid(format!("{what} is a list: object arrays are not supported")))
            }
            _ => Err(self.invalid(format!("{what} must be bytes, got {}", self.kind(v)))),
        }
    }

    fn tuple_of(&self, v: Val, what: &str) -> Res<&[Val]> {
        match self.obj(v) {
            Some(Obj::Tuple(items)) => Ok(items),
            _ => Err(self.invalid(format!("{what} must be a tuple, got {}", self.kind(v)))),
        }
    }

    fn shape_of(&self, v: Val) -> Res<Vec<usize>> {
        self.tuple_of(v, "array shape")?
            .iter()
            .map(|&d| match d {
                Val::Int(n) => usize::try_from(n)
                    .map_err(|_| self.invalid(format!("negative array dimension {n}"))),
                other => Err(self
                    .invalid(format!("array dimensions must be ints, got {}", self.kind(other)))),
            })
            .collect()
    }

    fn dtype_of(&self, v: Val) -> Res<(DType, ByteOrder)> {
        match self.obj(v) {
            Some(Obj::Dtype { dtype, order, code }) => match order {
                Some(o) => Ok((*dtype, *o)),
                None if dtype.itemsize() == 1 => Ok((*dtype, ByteOrder::NotApplicable)),
                // numpy always pickles a dtype's byte order in its BUILD state; without it the
                // bytes could be either.
                None => Err(self.invalid(format!(
                    "numpy.dtype('{code}') has no byte order (its BUILD state is missing)"
                ))),
            },
            _ => Err(self.invalid(format!("expected a numpy.dtype, got {}", self.kind(v)))),
        }
    }

    // --- running --------------------------------------------------------------------------------

    pub(super) fn run(mut self) -> Res<PyValue> {
        loop {
            self.op_at = self.pos;
            let Some(&code) = self.input.get(self.pos) else {
                return Err(PickleError::NoStop { offset: self.pos });
            };
            self.pos += 1;
            let Some(name) = opcode_name(code) else {
                return Err(PickleError::UnknownOpcode { offset: self.op_at, byte: code });
            };
            self.op_name = name;
            if code == op::STOP {
                return self.finish();
            }
            self.step(code)?;
        }
    }

    fn step(&mut self, code: u8) -> Res<()> {
        match code {
            op::PROTO => {
                let [v] = self.fixed::<1>()?;
                if v > MAX_PROTOCOL {
                    return Err(self.invalid(format!("protocol {v} is newer than {MAX_PROTOCOL}")));
                }
            }
            // Frames only tell a streaming reader how much to buffer; the whole input is already
            // in memory, and ignoring them lets a truncated file be reported at the opcode that
            // actually runs out of bytes.
            op::FRAME => {
                self.fixed::<8>()?;
            }
            op::MARK => self.marks.push(self.stack.len()),
            op::POP => {
                // As Python: POP right after a MARK discards the mark.
                if self.stack.len() > self.floor() {
                    self.pop()?;
                } else {
                    self.pop_mark()?;
                }
            }
            op::POP_MARK => {
                self.pop_mark()?;
            }
            op::DUP => {
                let v = self.top()?;
                self.push(v);
            }
            op::NONE => self.push(Val::None),
            op::NEWTRUE => self.push(Val::Bool(true)),
            op::NEWFALSE => self.push(Val::Bool(false)),
            op::BININT => {
                let b = self.fixed::<4>()?;
                self.push(Val::Int(i64::from(i32::from_le_bytes(b))));
            }
            op::BININT1 => {
                let [b] = self.fixed::<1>()?;
                self.push(Val::Int(i64::from(b)));
            }
            op::BININT2 => {
                let b = self.fixed::<2>()?;
                self.push(Val::Int(i64::from(u16::from_le_bytes(b))));
            }
            op::LONG1 => {
                let digits = self.payload(1)?;
                let v = self.long(digits)?;
                self.push(Val::Int(v));
            }
            op::LONG4 => {
                let n = i32::from_le_bytes(self.fixed::<4>()?);
                let n = usize::try_from(n)
                    .map_err(|_| self.invalid(format!("negative LONG4 length {n}")))?;
                let digits = self.take(n, || format!("length {n}"))?;
                let v = self.long(digits)?;
                self.push(Val::Int(v));
            }
            op::BINFLOAT => {
                let b = self.fixed::<8>()?;
                self.push(Val::Float(f64::from_be_bytes(b)));
            }
            op::SHORT_BINUNICODE => self.string(1)?,
            op::BINUNICODE => self.string(4)?,
            op::BINUNICODE8 => self.string(8)?,
            op::SHORT_BINBYTES => self.bytes(1)?,
            op::BINBYTES => self.bytes(4)?,
            op::BINBYTES8 | op::BYTEARRAY8 => self.bytes(8)?,
            op::EMPTY_LIST => {
                let v = self.new_obj(Obj::List(Vec::new()));
                self.push(v);
            }
            op::EMPTY_DICT => {
                let v = self.new_obj(Obj::Dict(Vec::new()));
                self.push(v);
            }
            op::EMPTY_TUPLE => {
                let v = self.new_obj(Obj::Tuple(Vec::new()));
                self.push(v);
            }
            op::LIST => {
                let items = self.pop_mark()?;
                let v = self.new_obj(Obj::List(items));
                self.push(v);
            }
            op::TUPLE => {
                let items = self.pop_mark()?;
                let v = self.new_obj(Obj::Tuple(items));
                self.push(v);
            }
            op::TUPLE1 | op::TUPLE2 | op::TUPLE3 => {
                let items = self.pop_n(usize::from(code - op::TUPLE1 + 1))?;
                let v = self.new_obj(Obj::Tuple(items));
                self.push(v);
            }
            op::DICT => {
                let items = self.pop_mark()?;
                let pairs = self.pairs(items)?;
                let v = self.new_obj(Obj::Dict(pairs));
                self.push(v);
            }
            op::APPEND => {
                let item = self.pop()?;
                self.extend_list(vec![item])?;
            }
            op::APPENDS => {
                let items = self.pop_mark()?;
                self.extend_list(items)?;
            }
            op::SETITEM => {
                let items = self.pop_n(2)?;
                let pairs = self.pairs(items)?;
                self.extend_dict(pairs)?;
            }
            op::SETITEMS => {
                let items = self.pop_mark()?;
                let pairs = self.pairs(items)?;
                self.extend_dict(pairs)?;
            }
            op::BINPUT => {
                let [i] = self.fixed::<1>()?;
                self.put(u32::from(i))?;
            }
            op::LONG_BINPUT => {
                let i = u32::from_le_bytes(self.fixed::<4>()?);
                self.put(i)?;
            }
            op::MEMOIZE => {
                // The memo has at most one entry per opcode, so this fits u32 for any input
                // under 4 GiB; beyond that, refuse rather than wrap.
                let i = u32::try_from(self.memo.len())
                    .map_err(|_| self.invalid("more than 2^32 memo entries"))?;
                self.put(i)?;
            }
            op::BINGET => {
                let [i] = self.fixed::<1>()?;
                self.get(u32::from(i))?;
            }
            op::LONG_BINGET => {
                let i = u32::from_le_bytes(self.fixed::<4>()?);
                self.get(i)?;
            }
            op::GLOBAL => {
                let module = self.line("module name")?;
                let name = self.line("global name")?;
                self.global(module, name)?;
            }
            op::STACK_GLOBAL => {
                let name_v = self.pop()?;
                let module_v = self.pop()?;
                let name = self.str_of(name_v, "STACK_GLOBAL name")?.to_owned();
                let module = self.str_of(module_v, "STACK_GLOBAL module")?.to_owned();
                self.global(&module, &name)?;
            }
            op::REDUCE => {
                let args_v = self.pop()?;
                let callable_v = self.pop()?;
                let callable = match self.obj(callable_v) {
                    Some(Obj::Callable(c)) => *c,
                    _ => {
                        return Err(self.invalid(format!(
                            "REDUCE needs a global to call, got {}",
                            self.kind(callable_v)
                        )))
                    }
                };
                let args = self.tuple_of(args_v, "REDUCE arguments")?.to_vec();
                let result = self.call(callable, &args)?;
                self.push(result);
            }
            op::BUILD => {
                let state = self.pop()?;
                let target = self.top()?;
                self.build(target, state)?;
            }
            other => {
                return Err(PickleError::UnsupportedOpcode {
                    offset: self.op_at,
                    opcode: self.op_name,
                    reason: unsupported_reason(other),
                })
            }
        }
        Ok(())
    }

    /// Python's LONG1/LONG4 payload: little-endian two's complement, any width. Only widths up to
    /// 64 bits are accepted (numpy shapes and the data never need more).
    fn long(&self, digits: &[u8]) -> Res<i64> {
        if digits.len() > 8 {
            return Err(
                self.invalid(format!("integer of {} bytes does not fit in 64 bits", digits.len()))
            );
        }
        let negative = digits.last().is_some_and(|&b| b & 0x80 != 0);
        let mut buf = if negative { [0xff; 8] } else { [0; 8] };
        for (dst, src) in buf.iter_mut().zip(digits) {
            *dst = *src;
        }
        Ok(i64::from_le_bytes(buf))
    }

    fn string(&mut self, len_size: usize) -> Res<()> {
        let raw = self.payload(len_size)?;
        let s =
            std::str::from_utf8(raw).map_err(|e| self.invalid(format!("invalid UTF-8: {e}")))?;
        let v = self.new_obj(Obj::Str(s.to_owned()));
        self.push(v);
        Ok(())
    }

    fn bytes(&mut self, len_size: usize) -> Res<()> {
        let raw = self.payload(len_size)?;
        let v = self.new_obj(Obj::Bytes(raw.to_vec()));
        self.push(v);
        Ok(())
    }

    fn pairs(&self, items: Vec<Val>) -> Res<Vec<(Val, Val)>> {
        if items.len() % 2 == 1 {
            return Err(self.invalid(format!("odd number of items ({}) for a dict", items.len())));
        }
        let mut it = items.into_iter();
        let mut pairs = Vec::with_capacity(it.len() / 2);
        while let (Some(k), Some(v)) = (it.next(), it.next()) {
            pairs.push((k, v));
        }
        Ok(pairs)
    }

    fn extend_list(&mut self, items: Vec<Val>) -> Res<()> {
        let target = self.top()?;
        let kind = self.kind(target);
        match target {
            Val::Obj(id) => match self.objs.get_mut(id) {
                Some(Obj::List(list)) => {
                    list.extend(items);
                    Ok(())
                }
                _ => Err(self.invalid(format!("can only append to a list, not a {kind}"))),
            },
            _ => Err(self.invalid(format!("can only append to a list, not a {kind}"))),
        }
    }

    fn extend_dict(&mut self, pairs: Vec<(Val, Val)>) -> Res<()> {
        let target = self.top()?;
        let kind = self.kind(target);
        match target {
            Val::Obj(id) => match self.objs.get_mut(id) {
                Some(Obj::Dict(dict)) => {
                    dict.extend(pairs);
                    Ok(())
                }
                _ => Err(self.invalid(format!("can only set items on a dict, not a {kind}"))),
            },
            _ => Err(self.invalid(format!("can only set items on a dict, not a {kind}"))),
        }
    }

    fn put(&mut self, index: u32) -> Res<()> {
        let v = self.top()?;
        self.memo.insert(index, v);
        Ok(())
    }

    fn get(&mut self, index: u32) -> Res<()> {
        let v = *self
            .memo
            .get(&index)
            .ok_or_else(|| self.invalid(format!("memo entry {index} does not exist")))?;
        self.push(v);
        Ok(())
    }

    fn global(&mut self, module: &str, name: &str) -> Res<()> {
        match Callable::lookup(module, name) {
            Some(c) => {
                let v = self.new_obj(Obj::Callable(c));
                self.push(v);
                Ok(())
            }
            None => Err(PickleError::GlobalNotAllowed {
                offset: self.op_at,
                opcode: self.op_name,
                module: clip(module),
                name: clip(name),
            }),
        }
    }

    /// The re-implementation of each allowed callable.
    fn call(&mut self, callable: Callable, args: &[Val]) -> Res<Val> {
        let wrong_args = |m: &Self| {
            m.invalid(format!("{}: unexpected arguments ({} given)", callable.name(), args.len()))
        };
        match callable {
            Callable::NdarrayType => Err(self
                .invalid("numpy.ndarray can only be passed to _reconstruct, not called directly")),
            Callable::Reconstruct => {
                let [class, _shape, _typecode] = args else { return Err(wrong_args(self)) };
                // The shape and type code are placeholders that BUILD overwrites; the class must
                // be ndarray itself (subclasses such as np.matrix would need their own code).
                match self.obj(*class) {
                    Some(Obj::Callable(Callable::NdarrayType)) => {
                        Ok(self.new_obj(Obj::PendingArray))
                    }
                    _ => Err(self.invalid(format!(
                        "_reconstruct of {} (only numpy.ndarray is supported)",
                        self.kind(*class)
                    ))),
                }
            }
            Callable::Dtype => {
                // numpy passes (code, align, copy); align and copy do not change the data.
                let Some(code_v) = args.first().filter(|_| args.len() <= 3) else {
                    return Err(wrong_args(self));
                };
                let code = clip(self.str_of(*code_v, "numpy.dtype type code")?);
                let (order, bare) = match code.as_bytes().first() {
                    Some(b'<') => (Some(ByteOrder::Little), code.get(1..)),
                    Some(b'>') => (Some(ByteOrder::Big), code.get(1..)),
                    Some(b'|') => (Some(ByteOrder::NotApplicable), code.get(1..)),
                    _ => (None, Some(code.as_str())),
                };
                let dtype = DType::from_code(bare.unwrap_or_default())
                    .map_err(|why| self.invalid(format!("numpy.dtype('{code}'): {why}")))?;
                Ok(self.new_obj(Obj::Dtype { dtype, order, code }))
            }
            Callable::Scalar => {
                let [dtype_v, data_v] = args else { return Err(wrong_args(self)) };
                let (dtype, order) = self.dtype_of(*dtype_v)?;
                let array = self.make_array(dtype, order, Vec::new(), false, *data_v)?;
                Ok(self.new_obj(Obj::Array(array)))
            }
            Callable::FromBuffer => self.call_frombuffer(args),
            Callable::CodecsEncode => {
                let [text_v, encoding_v] = args else { return Err(wrong_args(self)) };
                let encoding = self.str_of(*encoding_v, "_codecs.encode encoding")?;
                if encoding != "latin1" && encoding != "latin-1" {
                    return Err(self.invalid(format!(
                        "_codecs.encode with encoding '{}' (only latin1, as pickle writes bytes)",
                        clip(encoding)
                    )));
                }
                let text = self.str_of(*text_v, "_codecs.encode text")?;
                let out: Option<Vec<u8>> = text.chars().map(|c| u8::try_from(c).ok()).collect();
                let out = out.ok_or_else(|| {
                    self.invalid("_codecs.encode: text has characters beyond latin1")
                })?;
                self.charge(out.len())?;
                Ok(self.new_obj(Obj::Bytes(out)))
            }
            Callable::Bytes => {
                if !args.is_empty() {
                    return Err(self.invalid(
                        "builtins.bytes is only accepted with no arguments (protocol 2's b'')",
                    ));
                }
                Ok(self.new_obj(Obj::Bytes(Vec::new())))
            }
        }
    }

    /// `_frombuffer(buffer, dtype, shape, order[, axis_order])`, numpy's protocol-5 form:
    /// `frombuffer(buffer, dtype).reshape(shape, order=order)`, or with order 'K' the C-order
    /// buffer transposed by `axis_order`.
    fn call_frombuffer(&mut self, args: &[Val]) -> Res<Val> {
        let (buf_v, dtype_v, shape_v, order_v, axes_v) = match args {
            [b, d, s, o] => (*b, *d, *s, *o, None),
            [b, d, s, o, a] => (*b, *d, *s, *o, Some(*a)),
            _ => {
                return Err(self
                    .invalid(format!("_frombuffer: unexpected arguments ({} given)", args.len())))
            }
        };
        let (dtype, byte_order) = self.dtype_of(dtype_v)?;
        let shape = self.shape_of(shape_v)?;
        let order = self.str_of(order_v, "_frombuffer order")?.to_owned();
        let axes = match axes_v {
            Some(Val::None) | None => None,
            Some(a) => Some(self.shape_of(a)?),
        };
        let array = match (order.as_str(), axes) {
            ("C", None) => self.make_array(dtype, byte_order, shape, false, buf_v)?,
            ("F", None) => self.make_array(dtype, byte_order, shape, true, buf_v)?,
            ("K", Some(axes)) => {
                let c = self.make_array(dtype, byte_order, shape.clone(), false, buf_v)?;
                self.charge(c.data.len())?;
                let data =
                    permute_axes(&c.data, dtype.itemsize(), &shape, &axes).ok_or_else(|| {
                        self.invalid(format!(
                            "_frombuffer: axis order {axes:?} is not a permutation of the {} axes",
                            shape.len()
                        ))
                    })?;
                let out_shape = axes.iter().filter_map(|&a| shape.get(a).copied()).collect();
                NdArray { dtype, shape: out_shape, fortran_order: false, data }
            }
            _ => {
                return Err(self.invalid(format!(
                    "_frombuffer: order '{}' (expected 'C', 'F', or 'K' with an axis order)",
                    clip(&order)
                )))
            }
        };
        Ok(self.new_obj(Obj::Array(array)))
    }

    /// An array holding a copy of the bytes object `data_v`, after checking its size against the
    /// shape; big-endian data is converted to little-endian.
    fn make_array(
        &mut self,
        dtype: DType,
        order: ByteOrder,
        shape: Vec<usize>,
        fortran_order: bool,
        data_v: Val,
    ) -> Res<NdArray> {
        let len = self.bytes_of(data_v, "array data")?.len();
        let expected = shape
            .iter()
            .try_fold(dtype.itemsize(), |n, &d| n.checked_mul(d))
            .ok_or_else(|| self.invalid(format!("array shape {shape:?} overflows")))?;
        if expected != len {
            return Err(self.invalid(format!(
                "array of shape {shape:?} and dtype {dtype} needs {expected} bytes, got {len}"
            )));
        }
        self.charge(len)?;
        let mut data = self.bytes_of(data_v, "array data")?.to_vec();
        if order == ByteOrder::Big {
            for item in data.chunks_exact_mut(dtype.itemsize()) {
                item.reverse();
            }
        }
        Ok(NdArray { dtype, shape, fortran_order, data })
    }

    fn build(&mut self, target: Val, state: Val) -> Res<()> {
        let Val::Obj(id) = target else {
            return Err(self.invalid(format!("BUILD on a {}", self.kind(target))));
        };
        match self.objs.get(id) {
            Some(Obj::PendingArray) => {
                let array = self.array_state(state)?;
                if let Some(slot) = self.objs.get_mut(id) {
                    *slot = Obj::Array(array);
                }
                Ok(())
            }
            Some(Obj::Dtype { order: None, .. }) => {
                let new_order = self.dtype_state(id, state)?;
                if let Some(Obj::Dtype { order, .. }) = self.objs.get_mut(id) {
                    *order = Some(new_order);
                }
                Ok(())
            }
            Some(Obj::Dtype { .. }) => Err(self.invalid("numpy.dtype state set twice")),
            Some(Obj::Array(_)) => Err(self.invalid("numpy array state set twice")),
            _ => Err(self.invalid(format!(
                "BUILD on a {} (only numpy arrays and dtypes are supported)",
                self.kind(target)
            ))),
        }
    }

    /// ndarray.__setstate__: `(version, shape, dtype, is_fortran, rawdata)`, or the older form
    /// without `version`.
    fn array_state(&mut self, state: Val) -> Res<NdArray> {
        let items = self.tuple_of(state, "numpy array state")?;
        let (shape_v, dtype_v, fortran_v, data_v) = match items {
            [Val::Int(1), s, d, f, r] | [s, d, f, r] => (*s, *d, *f, *r),
            _ => {
                return Err(self.invalid(format!(
                    "numpy array state must be (1, shape, dtype, is_fortran, data), got {} items",
                    items.len()
                )))
            }
        };
        let shape = self.shape_of(shape_v)?;
        let (dtype, order) = self.dtype_of(dtype_v)?;
        let fortran = match fortran_v {
            Val::Bool(b) => b,
            Val::Int(i) => i != 0,
            other => {
                return Err(self.invalid(format!(
                    "numpy array is_fortran must be a bool, got {}",
                    self.kind(other)
                )))
            }
        };
        self.make_array(dtype, order, shape, fortran, data_v)
    }

    /// dtype.__setstate__: `(version, byteorder, subarray, names, fields, elsize, alignment,
    /// flags[, metadata])`. Only plain (non-structured) dtypes are accepted.
    fn dtype_state(&self, id: usize, state: Val) -> Res<ByteOrder> {
        let (dtype, code) = match self.objs.get(id) {
            Some(Obj::Dtype { dtype, code, .. }) => (*dtype, code.as_str()),
            _ => return Err(self.invalid("internal: not a dtype")),
        };
        let items = self.tuple_of(state, "numpy.dtype state")?;
        let [version, order_v, subarray, names, fields, ..] = items else {
            return Err(self.invalid(format!(
                "numpy.dtype('{code}') state has {} items, expected 8 or 9",
                items.len()
            )));
        };
        if !matches!(version, Val::Int(3 | 4)) {
            return Err(self.invalid(format!("numpy.dtype('{code}') state version must be 3 or 4")));
        }
        if ![subarray, names, fields].iter().all(|v| matches!(v, Val::None)) {
            return Err(self.invalid(format!(
                "numpy.dtype('{code}'): structured and subarray dtypes are not supported"
            )));
        }
        let order = match self.str_of(*order_v, "numpy.dtype byte order")? {
            "<" => ByteOrder::Little,
            ">" => ByteOrder::Big,
            "|" => ByteOrder::NotApplicable,
            other => {
                return Err(self.invalid(format!(
                    "numpy.dtype('{code}'): byte order '{}' (expected '<', '>' or '|')",
                    clip(other)
                )))
            }
        };
        if order == ByteOrder::NotApplicable && dtype.itemsize() > 1 {
            return Err(self.invalid(format!(
                "numpy.dtype('{code}'): byte order '|' for a {}-byte type",
                dtype.itemsize()
            )));
        }
        Ok(order)
    }

    fn finish(mut self) -> Res<PyValue> {
        if !self.marks.is_empty() {
            return Err(self.invalid("STOP with an unclosed MARK"));
        }
        let root = match self.stack.as_slice() {
            [v] => *v,
            other => {
                return Err(self
                    .invalid(format!("STOP with {} values on the stack, expected 1", other.len())))
            }
        };
        let mut tree = TreeBuilder {
            objs: &self.objs,
            budget: &mut self.budget,
            input_len: self.input.len(),
            op_at: self.op_at,
        };
        tree.value(root, 0)
    }
}

/// Keeps strings from the input short in error messages.
fn clip(s: &str) -> String {
    const MAX: usize = 200;
    match s.char_indices().nth(MAX) {
        Some((cut, _)) => format!("{}...", s.get(..cut).unwrap_or_default()),
        None => s.to_owned(),
    }
}
