"""What a compiled program does per execution, read off its optimized HLO: every kernel-level
instruction in a class, executed as often as its computation runs, with the bytes it moves and the
FLOPs of its matmuls. :mod:`wmjax.train.fit` prices a compiled train step with it
(:func:`step_cost`), and ``benchmarks/hlo_ops.py`` prints it as a table.

XLA's own ``cost_analysis()`` counts a ``while`` body once whatever its trip count, so a step whose
layers or micro-batches run in a ``lax.scan`` looks many times cheaper than it is; here a body
counts once per iteration.

Every kernel-level instruction (not the inside of a fusion) falls in one class, the first that
fits:

``matmul``     a cuBLAS call (``__cublas$gemm``, ``__cublas$lt$matmul``), a cuDNN convolution, a
               ``dot``, a ``convolution`` (as TPUs compile matmuls) or a fusion with either
               inside (XLA's Triton GEMM fusions, ``__triton_gemm``); with its FLOPs, 2·M·N·K
               from the dot's dimensions
``matmul_fp8`` a cuBLAS float8 GEMM (``__cublas$lt$matmul$f8``, :mod:`wmjax.nn.float8`); with its
               FLOPs, as a matmul's
``attention``  a cuDNN attention call (``__cudnn$fmha...``); with its FLOPs, from its score shape
``pallas``     a Pallas kernel lowered through Triton (``__gpu$xla.gpu.triton``), listed under its
               ``name=``
``memcpy``     a ``dynamic-slice`` or ``dynamic-update-slice`` that XLA's GPU compiler made a
               ``dynamic_slice_fusion`` custom fusion: a device-to-device memcpy at an offset
               computed on the host (the ``memcpy128`` kernels of a GPU profile). In a scan over
               layers these write each layer's residuals into the ``[layers, ...]`` stacks
``slice``      any other fusion whose root is a ``dynamic-slice`` or ``dynamic-update-slice``
               (a kernel: reading one layer's slice of those stacks, say)
``transpose``  a ``transpose``, a ``copy`` that changes the layout, or a fusion whose root (through
               bitcasts, converts and multi-output tuples) is one of those: pure data movement
``transposing`` a fusion that computes something and transposes inside (the transpose is not
               its root)
``copy``       a ``copy`` keeping its layout, ``copy-start``: a memcpy
``reduction``  a fusion with a ``reduce`` inside (XLA's ``kInput`` reduction fusions and its
               Triton normalization / softmax fusions), an unfused ``reduce``
``elementwise`` any other ``kLoop`` fusion or Triton (``__triton``) fusion
``collective`` an all-reduce, all-gather, reduce-scatter, all-to-all, collective-permute,
               send or recv
``other``      any other kernel: concatenate and scatter fusions, other custom calls, unfused ops

Instructions in a ``while`` body count once per iteration (``known_trip_count``; 1 when XLA does
not know it), so a scan over 14 layers counts its body 14 times. Bytes moved are bytes written
plus bytes read: the output (for a ``dynamic-update-slice`` root the update; for a custom call
not its scratch workspace, a trailing ``s8[n]`` / ``u8[n]``) and the operands (for a slice root
the slice itself, not the whole buffer). The bytes of a kernel that tiles its operands and reads
them more than once (a matmul, a Pallas kernel) are what it would move reading each once, a lower
bound on its traffic. The table groups kernels by class, output shape and the JAX op (``op_name``
metadata) they came from; the summary after it adds up each class, the total, and the total
outside the matmuls (the Pallas kernels' own matmuls included there).
"""

from __future__ import annotations

import collections
import dataclasses
import re

BYTES = {"pred": 1, "s8": 1, "u8": 1, "s16": 2, "u16": 2, "f16": 2, "bf16": 2, "s32": 4, "u32": 4,
         "f32": 4, "s64": 8, "u64": 8, "f64": 8, "c64": 8, "c128": 16, "f8e4m3fn": 1,
         "f8e5m2": 1, "s4": 1, "u4": 1}
_ARRAY = re.compile(r"\b([a-z]+\d*[a-z0-9]*)\[([\d,]*)\](\{[^}]*\})?")
_HEADER = re.compile(r"^(ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$")
_CALLS = re.compile(r"\b(calls|body|condition|to_apply|true_computation|false_computation)="
                    r"%?([\w.\-]+)")
_BRANCHES = re.compile(r"\b(?:branch_computations|called_computations)=\{([^}]*)\}")
_TRIP = re.compile(r'"known_trip_count":\{"n":"(\d+)"')
_OP_NAME = re.compile(r'op_name="([^"]*)"')
_TARGET = re.compile(r'custom_call_target="([^"]*)"')
_PALLAS_NAME = re.compile(r'\bname = "([\w.\-]+)"')
_DIM_LABELS = re.compile(r"\bdim_labels=\w+_(\w+)->\w+")
_SCORES = re.compile(r'"intermediate_tensor_shape":\s*\{[^{}]*?"dimensions":\s*\[([^\]]*)\]')
_CONTRACTING = re.compile(r'(?:lhs_contracting_dims=\{|"lhs_contracting_dimensions":\[)([^}\]]*)')
CLASSES = ("matmul", "matmul_fp8", "attention", "pallas", "memcpy", "slice", "transpose", "transposing", "copy",
           "reduction", "elementwise", "collective", "other")
# Ops a fusion root is looked through to find what the kernel does (and copies keeping the layout).
_THROUGH = ("bitcast", "convert", "tuple", "get-tuple-element")
# Kernel-level ops that launch no kernel: bookkeeping, control flow (whose bodies are counted on
# their own), the second halves of asynchronous pairs.
_NO_KERNEL = ("parameter", "constant", "get-tuple-element", "tuple", "bitcast", "while",
              "conditional", "call", "after-all", "add-dependency", "opt-barrier", "domain",
              "partition-id", "replica-id", "async-start", "async-update", "async-done",
              "copy-done", "all-reduce-done", "all-gather-done", "collective-permute-done",
              "send-done", "recv-done")
_COLLECTIVE = ("all-reduce", "all-reduce-start", "all-gather", "all-gather-start", "reduce-scatter",
               "all-to-all", "ragged-all-to-all", "collective-permute", "collective-permute-start",
               "collective-broadcast", "send", "recv")
_MATMULS = ("matmul", "matmul_fp8")
# Custom-call targets by prefix, first match: (prefix, class).
_TARGETS = (("__cublas$lt$matmul$f8", "matmul_fp8"), ("__cublas$", "matmul"),
            ("__cudnn$conv", "matmul"), ("__cudnn$fmha", "attention"),
            ("__gpu$xla.gpu.triton", "pallas"))


@dataclasses.dataclass
class Instruction:
  """One HLO instruction: ``shape`` is the text of its shape, ``operands`` their names."""

  name: str
  shape: str
  opcode: str
  operands: list[str]
  attributes: str
  root: bool


def _balanced(text: str, start: int) -> int:
  """Index just past the parenthesis group opening at ``text[start]``."""
  depth = 0
  for i in range(start, len(text)):
    depth += {"(": 1, ")": -1}.get(text[i], 0)
    if depth == 0:
      return i + 1
  return len(text)


def _split_top(text: str) -> list[str]:
  """``text`` split at the commas outside brackets, braces and parentheses."""
  parts, depth, current = [], 0, []
  for ch in text:
    depth += {"(": 1, "[": 1, "{": 1, ")": -1, "]": -1, "}": -1}.get(ch, 0)
    if ch == "," and depth == 0:
      parts.append("".join(current))
      current = []
    else:
      current.append(ch)
  if "".join(current).strip():
    parts.append("".join(current))
  return parts


def parse_instruction(line: str) -> Instruction | None:
  """An :class:`Instruction` from one line of HLO text, or None for any other line."""
  body = line.strip()
  root = body.startswith("ROOT ")
  if root:
    body = body[5:]
  name, sep, rest = body.partition(" = ")
  if not sep or " " in name.strip():
    return None
  end = _balanced(rest, 0) if rest.startswith("(") else rest.find(" ")
  if end <= 0:
    return None
  shape, rest = rest[:end], rest[end:].lstrip()
  paren = rest.find("(")
  if paren <= 0:
    return None
  opcode = rest[:paren]
  close = _balanced(rest, paren)
  operands = [part.split()[-1].lstrip("%") for part in _split_top(rest[paren + 1:close - 1])
              if part.split()]
  return Instruction(name.lstrip("%"), shape, opcode, operands, rest[close:], root)


def parse_module(text: str) -> tuple[dict[str, list[Instruction]], str]:
  """``({computation: instructions}, entry computation name)`` of an HLO module's text."""
  computations, entry, current = {}, None, None
  for line in text.splitlines():
    header = _HEADER.match(line)
    if header and " = " not in line.split("{")[0]:
      current = header.group(2)
      computations[current] = []
      if header.group(1):
        entry = current
      continue
    if current is not None:
      instruction = parse_instruction(line)
      if instruction is not None:
        computations[current].append(instruction)
  if entry is None:
    raise ValueError("no ENTRY computation in the HLO text")
  return computations, entry


def arrays(shape: str) -> list[tuple[str, tuple[int, ...], str]]:
  """``(dtype, dims, layout)`` of every array in a shape's text (several for a tuple)."""
  return [(dtype, tuple(int(d) for d in dims.split(",") if d), layout or "")
          for dtype, dims, layout in _ARRAY.findall(shape) if dtype in BYTES]


def _elements(dims: tuple[int, ...]) -> int:
  count = 1
  for d in dims:
    count *= d
  return count


def nbytes(shape: str) -> int:
  return sum(BYTES[dtype] * _elements(dims) for dtype, dims, _ in arrays(shape))


def executions(computations: dict[str, list[Instruction]], entry: str) -> dict[str, int]:
  """How many times each kernel-level computation runs per execution of ``entry``: ``while``
  bodies and conditions times their known trip count, called computations as often as their
  caller. Fusion computations and those applied element by element (``to_apply=`` of a reduce,
  an all-reduce, a sort) are left out: their instructions are not kernels."""
  counts = collections.Counter({entry: 1})
  order = [entry]
  for name in order:
    for inst in computations.get(name, []):
      if inst.opcode == "fusion":
        continue
      trip = _TRIP.search(inst.attributes)
      times = counts[name] * (int(trip.group(1)) if inst.opcode == "while" and trip else 1)
      callees = [m.group(2) for m in _CALLS.finditer(inst.attributes)
                 if m.group(1) != "to_apply" or inst.opcode == "call"]
      for group in _BRANCHES.findall(inst.attributes):
        callees += [c.strip().lstrip("%") for c in group.split(",") if c.strip()]
      for callee in callees:
        if callee in computations:
          if callee not in counts:
            order.append(callee)
          counts[callee] += times
  return dict(counts)


def _root(body: list[Instruction]) -> Instruction:
  return next((i for i in body if i.root), body[-1])


def _heroes(body: list[Instruction]) -> list[Instruction]:
  """What a fused computation's root does, looking through bitcasts, converts, tuples and copies
  that keep the layout."""
  named = {i.name: i for i in body}
  shapes = {i.name: i.shape for i in body}
  found, todo = [], [_root(body)]
  while todo:
    inst = todo.pop()
    if inst.opcode in _THROUGH or (inst.opcode == "copy" and not _layout_changes(inst, shapes)):
      todo += [named[o] for o in inst.operands if o in named]
    else:
      found.append(inst)
  return found


def _layout_changes(inst: Instruction, shapes: dict[str, str]) -> bool:
  """Whether a ``copy`` writes a layout other than its operand's."""
  source = arrays(shapes.get(inst.operands[0], "")) if inst.operands else []
  return not source or source[0][2] != arrays(inst.shape)[0][2]


@dataclasses.dataclass
class Kernel:
  """What one kernel-level instruction does per execution: its class, bytes written and read,
  FLOPs (matmuls only) and, for a Pallas kernel, its name."""

  cls: str
  written: int
  read: int
  flops: int = 0
  name: str | None = None


def _written(inst: Instruction) -> int:
  """Bytes of an instruction's output; a custom call's trailing scratch buffer (``s8[n]``, ``u8[n]``
  of a cuBLAS or cuDNN call's output tuple) is workspace, not output."""
  outputs = arrays(inst.shape)
  if (inst.opcode == "custom-call" and len(outputs) > 1 and outputs[-1][0] in ("s8", "u8")
      and len(outputs[-1][1]) == 1):
    outputs = outputs[:-1]
  return sum(BYTES[dtype] * _elements(dims) for dtype, dims, _ in outputs)


def _flops(inst: Instruction, shapes: dict[str, str]) -> int:
  """2·M·N·K of a ``dot`` or cuBLAS call: twice its output's elements times the contracted size
  (of a ``convolution``, as TPUs compile matmuls: the kernel's elements per output feature)."""
  if inst.opcode == "convolution":
    labels = _DIM_LABELS.search(inst.attributes)
    kernel = arrays(shapes.get(inst.operands[1], "")) if len(inst.operands) > 1 else []
    if not labels or not kernel or not arrays(inst.shape) or "o" not in labels.group(1):
      return 0
    per_output = _elements(kernel[0][1]) // max(1, kernel[0][1][labels.group(1).index("o")])
    return 2 * _elements(arrays(inst.shape)[0][1]) * per_output
  contracting = _CONTRACTING.search(inst.attributes)
  lhs = arrays(shapes.get(inst.operands[0], "")) if inst.operands else []
  if not contracting or not lhs or not arrays(inst.shape):
    return 0
  k = _elements(tuple(lhs[0][1][int(d.strip(' "'))] for d in contracting.group(1).split(",")
                      if d.strip(' "')))
  return 2 * _elements(arrays(inst.shape)[0][1]) * k


def _attention_flops(inst: Instruction, shapes: dict[str, str]) -> int:
  """FLOPs of a cuDNN attention call: two score-sized matmuls forward (``Q K^T``, ``P V``), five
  backward (the scores recomputed, then the gradients of ``P``, ``V``, ``Q`` and ``K``), each
  2·(batch·heads·queries·keys)·head_dim, from the call's score shape and its query operand."""
  scores = _SCORES.search(inst.attributes)
  query = arrays(shapes.get(inst.operands[0], "")) if inst.operands else []
  if not scores or not query:
    return 0
  dims = [int(d.strip(' "')) for d in scores.group(1).split(",") if d.strip(' "')]
  head_dim = _elements(query[0][1]) // max(1, _elements(tuple(dims[:-1])))
  matmuls = 5 if _TARGET.search(inst.attributes).group(1).endswith("Backward") else 2
  return matmuls * 2 * _elements(tuple(dims)) * head_dim


def _target_class(inst: Instruction) -> str | None:
  target = _TARGET.search(inst.attributes)
  return next((cls for prefix, cls in _TARGETS
               if target and target.group(1).startswith(prefix)), None)


def classify(inst: Instruction, computations: dict[str, list[Instruction]],
             shapes: dict[str, str]) -> Kernel | None:
  """The :class:`Kernel` of a kernel-level instruction, None for one that launches no kernel."""
  if inst.opcode in _NO_KERNEL:
    return None
  written = _written(inst)
  if inst.opcode == "fusion":
    return _classify_fusion(inst, computations, written)
  read = sum(nbytes(shapes.get(o, "")) for o in inst.operands)
  if inst.opcode in ("dot", "convolution"):
    return Kernel("matmul", written, read, _flops(inst, shapes))
  if inst.opcode == "custom-call":
    cls = _target_class(inst) or "other"
    if cls == "pallas":
      name = _PALLAS_NAME.search(inst.attributes)
      return Kernel(cls, written, read, name=name.group(1) if name else None)
    if cls == "attention":
      return Kernel(cls, written, read, _attention_flops(inst, shapes))
    return Kernel(cls, written, read, _flops(inst, shapes) if cls in _MATMULS else 0)
  if inst.opcode == "transpose":
    return Kernel("transpose", written, read)
  if inst.opcode == "copy":
    return Kernel("transpose" if _layout_changes(inst, shapes) else "copy", written, read)
  if inst.opcode == "copy-start":
    return Kernel("copy", read, read)  # its output is (source, destination, context)
  if inst.opcode in _COLLECTIVE:
    if inst.opcode in ("all-gather-start", "collective-permute-start"):
      written -= read  # their output tuple repeats the operands before the results
    return Kernel("collective", written, read)
  return Kernel("reduction" if inst.opcode == "reduce" else "other", written, read)


def _classify_fusion(inst: Instruction, computations: dict[str, list[Instruction]],
                     written: int) -> Kernel:
  """The :class:`Kernel` of a fusion, from the instructions of its fused computation."""
  called = _CALLS.search(inst.attributes)
  body = computations.get(called.group(2), []) if called else []
  fused_shapes = {i.name: i.shape for i in body}
  read = _fusion_reads(body)
  matmuls = [i for i in body if i.opcode in ("dot", "convolution")
             or (i.opcode == "custom-call" and _target_class(i) in _MATMULS)]
  if matmuls:
    return Kernel("matmul", written, read, sum(_flops(i, fused_shapes) for i in matmuls))
  heroes = _heroes(body) if body else []
  slices = [h for h in heroes if h.opcode in ("dynamic-slice", "dynamic-update-slice")]
  if slices:
    moved = sum(nbytes(fused_shapes.get(h.operands[1], "")) if h.opcode == "dynamic-update-slice"
                else nbytes(h.shape) for h in slices)
    custom = '"name":"dynamic_slice_fusion"' in inst.attributes
    return Kernel("memcpy" if custom else "slice", moved, moved)
  if any(h.opcode == "transpose" or (h.opcode == "copy" and _layout_changes(h, fused_shapes))
         for h in heroes):
    return Kernel("transpose", written, read)
  if any(i.opcode == "transpose" for i in body):
    return Kernel("transposing", written, read)
  if any(i.opcode == "reduce" for i in body):
    return Kernel("reduction", written, read)
  if "kind=kLoop" in inst.attributes or '"kind":"__triton"' in inst.attributes:
    return Kernel("elementwise", written, read)
  return Kernel("other", written, read)


def _fusion_reads(body: list[Instruction]) -> int:
  """Bytes a fusion reads: each parameter in full, except those only sliced (``dynamic-slice``:
  the slices) or updated in place (``dynamic-update-slice``: nothing), through bitcasts."""
  users = collections.defaultdict(list)
  for inst in body:
    for position, operand in enumerate(inst.operands):
      users[operand].append((inst, position))
  def uses_of(name):  # through bitcasts, which move no data
    found = []
    for user, position in users[name]:
      found += uses_of(user.name) if user.opcode == "bitcast" else [(user, position)]
    return found

  total = 0
  for param in (i for i in body if i.opcode == "parameter"):
    uses = uses_of(param.name)
    if uses and all(u.opcode in ("dynamic-slice", "dynamic-update-slice") and position == 0
                    for u, position in uses):
      total += sum(nbytes(u.shape) for u, _ in uses if u.opcode == "dynamic-slice")
    else:
      total += nbytes(param.shape)
  return total


@dataclasses.dataclass
class Row:
  """Kernels of one class, output shape and JAX op (a Pallas kernel's name): ``count`` executions
  per run, bytes moved, FLOPs."""

  cls: str
  shape: str
  op: str
  count: int = 0
  moved: int = 0
  flops: int = 0


def analyze(text: str) -> list[Row]:
  """The kernels of an optimized HLO module, grouped, most bytes first."""
  computations, entry = parse_module(text)
  rows: dict[tuple[str, str, str], Row] = {}
  for name, times in executions(computations, entry).items():
    body = computations[name]
    shapes = {i.name: i.shape for i in body}
    for inst in body:
      kernel = classify(inst, computations, shapes)
      if kernel is None:
        continue
      op_name = _OP_NAME.search(inst.attributes)
      op = kernel.name or (_short_op(op_name.group(1)) if op_name else "?")
      shape = " ".join(f"{dtype}[{','.join(map(str, dims))}]{layout}"
                       for dtype, dims, layout in arrays(inst.shape))
      row = rows.setdefault((kernel.cls, shape, op), Row(kernel.cls, shape, op))
      row.count += times
      row.moved += times * (kernel.written + kernel.read)
      row.flops += times * kernel.flops
  return sorted(rows.values(), key=lambda r: -r.moved)


def _short_op(op_name: str) -> str:
  """A JAX op name without the ``jit(step)/...`` prefix up to the model's modules."""
  parts = op_name.split("/")
  keep = [p for p in parts if not p.startswith(("jit(", "jvp(", "transpose(", "while", "body",
                                                  "closed_call", "checkpoint", "rematted"))]
  direction = "bwd " if any(p.startswith("transpose(") for p in parts) else ""
  return direction + "/".join(keep[-5:])


def summary(rows: list[Row]) -> dict[str, dict[str, float]]:
  """``{class: {'kernels': executions per run, 'gb': GB moved per run, 'tflop': TFLOPs per run}}``
  for every class, their ``total`` and the total ``outside matmul`` (outside both matmul
  classes)."""
  out = {cls: {"kernels": 0, "gb": 0.0, "tflop": 0.0}
         for cls in CLASSES + ("total", "outside matmul")}
  for row in rows:
    for cls in (row.cls, "total") + (() if row.cls in _MATMULS else ("outside matmul",)):
      out[cls]["kernels"] += row.count
      out[cls]["gb"] += row.moved / 1e9
      out[cls]["tflop"] += row.flops / 1e12
  return out


def step_cost(text: str) -> dict[str, float]:
  """``{'matmul_flops', 'fp8_matmul_flops', 'matmul_bytes', 'other_bytes', 'kernels'}`` per
  execution of the optimized HLO ``text``: the FLOPs and bytes of its matmuls (float8 GEMMs
  included; their FLOPs also apart), the bytes every other kernel moves, and the kernels it
  launches."""
  totals = summary(analyze(text))
  return {"matmul_flops": sum(totals[cls]["tflop"] for cls in _MATMULS) * 1e12,
          "fp8_matmul_flops": totals["matmul_fp8"]["tflop"] * 1e12,
          "matmul_bytes": sum(totals[cls]["gb"] for cls in _MATMULS) * 1e9,
          "other_bytes": totals["outside matmul"]["gb"] * 1e9,
          "kernels": totals["total"]["kernels"]}
