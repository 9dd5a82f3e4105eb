"""Transposes and copies of a compiled program, from its optimized HLO, counted per execution.

  python benchmarks/hlo_ops.py --config configs/irasim.py:XL --target h100 --batch 16 \
      --config.model.dtype=bfloat16 --config.model.attention_impl=auto \
      --config.model.remat=dots [--save_hlo /tmp/xl.hlo] [--top 40]
  python benchmarks/hlo_ops.py --hlo /tmp/xl.hlo

The first form compiles the train step of a config for a device target as ``wmjax compile`` does
(:func:`wmjax.train.fit.compile_step`; no hardware needed) and reads ``compiled.as_text()``; the
second reads HLO text saved before. For an H100 target without a GPU, set
``XLA_FLAGS="--xla_gpu_enable_triton_gemm=false --xla_gpu_autotune_level=0"``: without autotuning
the Triton GEMM emitter can fail to tile some matmuls.

Every kernel-level instruction (not the inside of a fusion) falls in one class:

``transpose``  a ``transpose``, a ``copy`` that changes the layout, or a fusion whose root (through
               bitcasts, converts and multi-output tuples) is one of those: pure data movement
``transposing`` a fusion that computes something and transposes inside (the transpose is not
               its root): its bytes are those that pass through the transposes, read and written
``copy``       a ``copy`` keeping its layout, ``copy-start``: a memcpy
``memcpy``     a ``dynamic-slice`` or ``dynamic-update-slice`` that XLA's GPU compiler made a
               ``dynamic_slice_fusion`` custom fusion: a device-to-device memcpy at an offset
               computed on the host (the ``memcpy128`` kernels of a GPU profile). In a scan over
               layers these write each layer's residuals into the ``[layers, ...]`` stacks
``slice``      any other fusion whose root is a ``dynamic-slice`` or ``dynamic-update-slice``
               (a kernel: reading one layer's slice of those stacks, say)

Instructions in a ``while`` body count once per iteration (``known_trip_count``; 1 when XLA does
not know it), so a scan over 14 layers counts its body 14 times. Bytes moved are bytes written
plus bytes read: the output (for a ``dynamic-update-slice`` root the update) and the fusion's
operands (for a slice root the slice itself, not the whole buffer). The table groups kernels by
class, output shape and the JAX op (``op_name`` metadata) they came from.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import re
import sys

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
CLASSES = ("transpose", "transposing", "copy", "memcpy", "slice")
# Ops a fusion root is looked through to find what the kernel does.
_THROUGH = ("bitcast", "convert", "tuple", "get-tuple-element")


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


def nbytes(shape: str) -> int:
  total = 0
  for dtype, dims, _ in arrays(shape):
    size = BYTES[dtype]
    for d in dims:
      size *= d
    total += size
  return total


def executions(computations: dict[str, list[Instruction]], entry: str) -> dict[str, int]:
  """How many times each kernel-level computation runs per execution of ``entry``: ``while``
  bodies and conditions times their known trip count, called computations as often as their
  caller. Fusion computations are left out (their instructions are not kernels)."""
  counts = collections.Counter({entry: 1})
  order = [entry]
  for name in order:
    for inst in computations.get(name, []):
      if inst.opcode == "fusion":
        continue
      trip = _TRIP.search(inst.attributes)
      times = counts[name] * (int(trip.group(1)) if inst.opcode == "while" and trip else 1)
      callees = [m.group(2) for m in _CALLS.finditer(inst.attributes)]
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
  """What a fused computation's root does, looking through bitcasts, converts and tuples."""
  named = {i.name: i for i in body}
  found, todo = [], [_root(body)]
  while todo:
    inst = todo.pop()
    if inst.opcode in _THROUGH:
      todo += [named[o] for o in inst.operands if o in named]
    else:
      found.append(inst)
  return found


def _layout_changes(inst: Instruction, shapes: dict[str, str]) -> bool:
  """Whether a ``copy`` writes a layout other than its operand's."""
  source = arrays(shapes.get(inst.operands[0], "")) if inst.operands else []
  return not source or source[0][2] != arrays(inst.shape)[0][2]


def classify(inst: Instruction, computations: dict[str, list[Instruction]],
             shapes: dict[str, str]) -> tuple[str, int, int] | None:
  """``(class, bytes written, bytes read)`` of a kernel-level instruction, None when it is none
  of :data:`CLASSES`."""
  written = nbytes(inst.shape)
  read = sum(nbytes(shapes.get(o, "")) for o in inst.operands)
  if inst.opcode == "transpose":
    return "transpose", written, read
  if inst.opcode == "copy":
    return ("transpose" if _layout_changes(inst, shapes) else "copy"), written, read
  if inst.opcode == "copy-start":
    return "copy", read, read  # its output is (source, destination, context)
  if inst.opcode != "fusion":
    return None
  called = _CALLS.search(inst.attributes)
  body = computations.get(called.group(2), []) if called else []
  if not body:
    return None
  fused_shapes = {i.name: i.shape for i in body}
  read = _fusion_reads(body)
  heroes = _heroes(body)
  slices = [h for h in heroes if h.opcode in ("dynamic-slice", "dynamic-update-slice")]
  if slices:
    moved = sum(nbytes(fused_shapes.get(h.operands[1], "")) if h.opcode == "dynamic-update-slice"
                else nbytes(h.shape) for h in slices)
    custom = '"name":"dynamic_slice_fusion"' in inst.attributes
    return ("memcpy" if custom else "slice"), moved, moved
  if any(h.opcode == "transpose" or (h.opcode == "copy" and _layout_changes(h, fused_shapes))
         for h in heroes):
    return "transpose", written, read
  transposed = sum(nbytes(i.shape) for i in body if i.opcode == "transpose")
  if transposed:
    return "transposing", transposed, transposed
  return None


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
  """Kernels of one class, output shape and JAX op: ``count`` executions per run, bytes moved."""

  cls: str
  shape: str
  op: str
  count: int = 0
  moved: int = 0


def analyze(text: str) -> list[Row]:
  """The transpose / copy kernels of an optimized HLO module, grouped, most bytes first."""
  computations, entry = parse_module(text)
  rows: dict[tuple[str, str, str], Row] = {}
  for name, times in executions(computations, entry).items():
    body = computations[name]
    shapes = {i.name: i.shape for i in body}
    for inst in body:
      found = classify(inst, computations, shapes)
      if found is None:
        continue
      cls, written, read = found
      op_name = _OP_NAME.search(inst.attributes)
      shape = " ".join(f"{dtype}[{','.join(map(str, dims))}]{layout}"
                       for dtype, dims, layout in arrays(inst.shape))
      key = (cls, shape, _short_op(op_name.group(1)) if op_name else "?")
      row = rows.setdefault(key, Row(*key))
      row.count += times
      row.moved += times * (written + read)
  return sorted(rows.values(), key=lambda r: -r.moved)


def _short_op(op_name: str) -> str:
  """A JAX op name without the ``jit(step)/...`` prefix up to the model's modules."""
  parts = op_name.split("/")
  keep = [p for p in parts if not p.startswith(("jit(", "jvp(", "transpose(", "while", "body",
                                                  "closed_call", "checkpoint", "rematted"))]
  direction = "bwd " if any(p.startswith("transpose(") for p in parts) else ""
  return direction + "/".join(keep[-5:])


def summary(rows: list[Row]) -> dict[str, dict[str, float]]:
  """``{class: {'kernels': executions per run, 'gb': GB moved per run}}`` and their total."""
  out = {cls: {"kernels": 0, "gb": 0.0} for cls in CLASSES + ("total",)}
  for row in rows:
    for cls in (row.cls, "total"):
      out[cls]["kernels"] += row.count
      out[cls]["gb"] += row.moved / 1e9
  return out


def report(rows: list[Row], top: int) -> str:
  lines = [f"{'class':<12}{'count':>6}{'GB':>9}  {'shape':<44}op"]
  for row in rows[:top]:
    lines.append(f"{row.cls:<12}{row.count:>6}{row.moved / 1e9:>9.3f}  {row.shape:<44}{row.op}")
  lines.append("")
  for cls, s in summary(rows).items():
    lines.append(f"{cls:<12}{s['kernels']:>6}{s['gb']:>9.3f}")
  return "\n".join(lines)


def compiled_text(config_spec: str, overrides: list[str], target_spec: str, batch: int | None
                  ) -> tuple[str, dict]:
  """Optimized HLO text and memory report of a config's train step compiled for a target."""
  import jax
  jax.config.update("jax_platforms", "cpu")
  from wmjax.config import load_config
  from wmjax.train import fit
  config = load_config(config_spec, overrides)
  _, compiled, memory = fit.compile_step(config, fit.parse_target(target_spec), batch)
  return compiled.as_text(), memory


def main() -> None:
  from wmjax.config import parse_args_with_overrides
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--hlo", default=None, help="read this HLO text instead of compiling")
  parser.add_argument("--config", default=None)
  parser.add_argument("--target", default="h100")
  parser.add_argument("--batch", type=int, default=None)
  parser.add_argument("--save_hlo", default=None, help="also write the compiled HLO text here")
  parser.add_argument("--top", type=int, default=40, help="table rows (most bytes first)")
  parser.add_argument("--json", action="store_true", help="print the summary as JSON too")
  args, overrides = parse_args_with_overrides(parser)
  memory = None
  if args.hlo:
    with open(args.hlo) as f:
      text = f.read()
  elif args.config:
    text, memory = compiled_text(args.config, overrides, args.target, args.batch)
    if args.save_hlo:
      with open(args.save_hlo, "w") as f:
        f.write(text)
  else:
    sys.exit("hlo_ops: give --hlo FILE or --config CONFIG")
  rows = analyze(text)
  print(report(rows, args.top))
  if memory is not None:
    print(f"compiled memory per device: {memory['total_gib']:.2f} GiB "
          f"(temporaries {memory['temp_gib']:.2f} GiB)")
  if args.json:
    print(json.dumps({"summary": summary(rows),
                      "total_gib": None if memory is None else memory["total_gib"]}))


if __name__ == "__main__":
  main()
