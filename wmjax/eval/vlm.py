"""A vision-language model as a success judge ("VLM as reward", WPE section 4 and appendix B.1).

A few frames of a rollout video and the task description go to a VLM behind an OpenAI-compatible
chat-completions endpoint (OpenAI, vLLM, SGLang, Ollama, ...) with the WPE prompt, which asks for
reasoning followed by ``Answer: Yes`` or ``Answer: No``. ``num_samples`` independent replies are
drawn (``n`` in the request) and the majority of the parseable ones decides.

- :data:`WPE_PROMPT`: the paper's prompt, with a ``{task_description}`` placeholder.
- :func:`parse_answer`: a reply -> True / False / None (no final answer found).
- :func:`subsample_frames`: ``count`` evenly spaced frames, the first and the last included.
- :class:`VLMJudge`: :meth:`VLMJudge.judge` scores one video as a :class:`Judgement`; calling the
  judge scores a batch ``[B, T, H, W, 3]`` concurrently and returns ``[B]`` rewards (1 success,
  0 failure, NaN when no reply could be parsed), the reward-function protocol of
  :class:`wmjax.env.WorldModelEnv`.

Only the standard library talks HTTP. Timeouts, connection errors, HTTP 429 and 5xx are retried
with exponential backoff; other HTTP errors fail at once. The API key goes in the
``Authorization`` header only: it is kept out of the judge's repr, the logs and the errors.
"""

from __future__ import annotations

import base64
import concurrent.futures
import dataclasses
import http.client
import io
import json
import logging
import os
import re
import time
import urllib.error
import urllib.request
from typing import Any, Sequence

import numpy as np
from PIL import Image

from wmjax.frames import to_uint8

logger = logging.getLogger(__name__)

WPE_PROMPT = (
    "Here is a sequence of frames from a policy rollout video. I need your help determining "
    "whether the policy is successful. Does the robot successfully complete the following task? "
    "Explain your reasoning, and then output Answer: Yes or Answer: No'. "
    "Task: {task_description} "
    "Note: The Task description may have been truncated a bit. "
    "Note: Since the video is low resolution, disregard specific object identities in the Task "
    "description when necessary. This is because the specific object may be hard to identify in "
    "the frames low level of detail. For example, if the task is \"Pick up the X and place it in "
    "the basket\", then any rollout which picks up any object and places it in the basket would "
    "be considered a success.")

_IMAGE_DETAILS = ("low", "high", "auto")
# "answer" then a colon or dash, with markdown / spaces around: "Answer:", "**Answer:**", "ANSWER -"
_ANSWER_MARK = re.compile(r"\banswer\b[\s*_]*[:\-\u2013\u2014]", re.IGNORECASE)
# the verdict right after the mark, possibly bold or quoted: " Yes", " **no**", " 'Yes'"
_VERDICT = re.compile(r"[\s*_\"'`]*(yes|no)\b", re.IGNORECASE)


class VLMError(RuntimeError):
  """The VLM endpoint failed: an HTTP error that is not retried, or every attempt failed."""


def parse_answer(text: str | None) -> bool | None:
  """The verdict of a reply: the last ``Answer:`` mark decides, True for yes, False for no.

  The mark tolerates case and markdown (``**Answer:** Yes``, ``answer - no.``); reasoning before
  it may mention yes or no freely. None when there is no mark or no yes / no right after the last
  one (``Answer: maybe``).
  """
  if not text:
    return None
  marks = list(_ANSWER_MARK.finditer(text))
  if not marks:
    return None
  verdict = _VERDICT.match(text, marks[-1].end())
  if verdict is None:
    return None
  return verdict.group(1).lower() == "yes"


def subsample_frames(frames, count: int) -> np.ndarray:
  """``count`` evenly spaced frames of ``[T, H, W, 3]`` (uint8, or floats in [-1, 1]), the first
  and the last included -> uint8 ``[min(T, count), H, W, 3]``. ``count = 1`` keeps the last frame,
  the outcome of the rollout."""
  frames = np.asarray(frames)
  if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 1:
    raise ValueError(f"expected frames [T, H, W, 3] with T >= 1, got shape {frames.shape}")
  if count < 1:
    raise ValueError(f"expected count >= 1, got {count}")
  total = frames.shape[0]
  if total <= count:
    return to_uint8(frames)
  if count == 1:
    return to_uint8(frames[-1:])
  # spacing (T - 1) / (count - 1) > 1 here, so the rounded indices are distinct
  indices = np.round(np.linspace(0, total - 1, count)).astype(int)
  return to_uint8(frames[indices])


def _png_data_url(frame: np.ndarray) -> str:
  """uint8 ``[H, W, 3]`` -> ``data:image/png;base64,...``."""
  buffer = io.BytesIO()
  Image.fromarray(np.ascontiguousarray(frame)).save(buffer, format="PNG")
  return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


@dataclasses.dataclass(frozen=True)
class Judgement:
  """The verdict on one video: ``success`` is the majority of the parseable votes (a tie is not a
  success; None when no vote parsed), from ``yes`` / ``no`` votes, ``unparsed`` replies and the
  raw ``replies``."""

  success: bool | None
  yes: int
  no: int
  unparsed: int
  replies: tuple[str, ...]

  @classmethod
  def from_replies(cls, replies: Sequence[str]) -> Judgement:
    votes = [parse_answer(reply) for reply in replies]
    yes, no = votes.count(True), votes.count(False)
    success = None if yes + no == 0 else yes > no
    return cls(success, yes, no, len(votes) - yes - no, tuple(replies))

  @property
  def reward(self) -> float:
    """1.0 for success, 0.0 for failure, NaN when no vote parsed."""
    return float("nan") if self.success is None else float(self.success)


def _server_message(error: urllib.error.HTTPError) -> str:
  """The server's error message: ``error.message`` of a JSON body, else the body's start."""
  text = error.read().decode("utf-8", errors="replace")
  try:
    detail = json.loads(text).get("error", text)
  except (ValueError, AttributeError):
    detail = text
  if isinstance(detail, dict):
    detail = detail.get("message", detail)
  return str(detail)[:500] or error.reason


def _retryable(error: Exception) -> bool:
  """Timeouts, connection errors, HTTP 429 and 5xx are worth another try."""
  if isinstance(error, urllib.error.HTTPError):
    return error.code == 429 or error.code >= 500
  if isinstance(error, urllib.error.URLError):
    return isinstance(error.reason, OSError)  # timeout, refused, DNS; not e.g. a bad URL scheme
  return isinstance(error, (OSError, http.client.HTTPException))


def _reply_texts(response: Any) -> list[str]:
  """The assistant text of every choice of a chat-completions response (None content -> "")."""
  choices = response.get("choices") if isinstance(response, dict) else None
  if not isinstance(choices, list) or not choices:
    raise VLMError(f"expected a chat-completions response with a non-empty 'choices' list, got "
                   f"{json.dumps(response)[:300]}")
  return [(choice.get("message") or {}).get("content") or "" for choice in choices]


@dataclasses.dataclass
class VLMJudge:
  """Success judge over an OpenAI-compatible chat-completions endpoint.

  ``base_url``: up to ``/v1`` (``/chat/completions`` is appended); ``api_key``: sent as a bearer
  token when set (None for local servers). Each video is shown as ``num_frames`` PNG frames at
  ``image_detail``; ``num_samples`` replies at ``temperature`` vote. Each HTTP request gets
  ``timeout`` seconds and ``max_retries`` attempts in all, ``backoff * 2**k`` seconds apart.
  ``prompt`` must contain ``{task_description}``. A batch uses up to ``max_workers`` threads.
  """

  base_url: str
  model: str
  api_key: str | None = dataclasses.field(default=None, repr=False)
  num_frames: int = 8
  num_samples: int = 3
  temperature: float = 1.0
  max_tokens: int = 512
  timeout: float = 60.0
  max_retries: int = 3
  backoff: float = 1.0
  prompt: str = WPE_PROMPT
  image_detail: str = "low"
  max_workers: int = 8

  def __post_init__(self):
    for name in ("num_frames", "num_samples", "max_tokens", "max_retries", "max_workers"):
      if getattr(self, name) < 1:
        raise ValueError(f"expected {name} >= 1, got {getattr(self, name)}")
    if self.timeout <= 0 or self.backoff < 0:
      raise ValueError(f"expected timeout > 0 and backoff >= 0, got timeout={self.timeout}, "
                       f"backoff={self.backoff}")
    if self.image_detail not in _IMAGE_DETAILS:
      raise ValueError(f"expected image_detail in {_IMAGE_DETAILS}, got {self.image_detail!r}")
    if "{task_description}" not in self.prompt:
      raise ValueError("expected a prompt with a {task_description} placeholder")

  @classmethod
  def from_env(cls, prefix: str = "WMJAX_VLM_", **overrides) -> VLMJudge:
    """A judge from ``{prefix}BASE_URL`` (else ``OPENAI_BASE_URL``, else OpenAI's API),
    ``{prefix}MODEL`` (else ``gpt-4o``) and ``{prefix}API_KEY`` (else ``OPENAI_API_KEY``, else
    none); keyword ``overrides`` set any field."""
    env = os.environ
    fields = {
        "base_url": (env.get(prefix + "BASE_URL") or env.get("OPENAI_BASE_URL")
                     or "https://api.openai.com/v1"),
        "model": env.get(prefix + "MODEL") or "gpt-4o",
        "api_key": env.get(prefix + "API_KEY") or env.get("OPENAI_API_KEY") or None,
    }
    return cls(**{**fields, **overrides})

  @property
  def url(self) -> str:
    """The chat-completions endpoint."""
    return self.base_url.rstrip("/") + "/chat/completions"

  def request_body(self, frames, task: str) -> dict[str, Any]:
    """The chat-completions request for one video ``[T, H, W, 3]``: one user message with the
    prompt for ``task`` then the subsampled frames as PNG data URLs, asking for ``num_samples``
    replies."""
    if not isinstance(task, str):
      raise TypeError(f"expected the task description as a str, got {type(task).__name__}")
    content = [{"type": "text", "text": self.prompt.replace("{task_description}", task)}]
    for frame in subsample_frames(frames, self.num_frames):
      content.append({"type": "image_url",
                      "image_url": {"url": _png_data_url(frame), "detail": self.image_detail}})
    return {"model": self.model, "messages": [{"role": "user", "content": content}],
            "temperature": self.temperature, "max_tokens": self.max_tokens,
            "n": self.num_samples}

  def _post(self, body: dict[str, Any]) -> dict[str, Any]:
    """POST ``body`` to the endpoint, retrying transient failures -> the decoded JSON reply."""
    data = json.dumps(body).encode("utf-8")
    headers = {"Content-Type": "application/json"}
    if self.api_key:
      headers["Authorization"] = f"Bearer {self.api_key}"
    last_error = ""
    for attempt in range(1, self.max_retries + 1):
      request = urllib.request.Request(self.url, data=data, headers=headers, method="POST")
      try:
        with urllib.request.urlopen(request, timeout=self.timeout) as response:
          return self._decode(response.read())
      except (OSError, http.client.HTTPException) as error:
        last_error = self._describe(error)
        if not _retryable(error):
          raise VLMError(f"VLM request to {self.url} failed: {last_error}") from None
        if attempt < self.max_retries:
          delay = self.backoff * 2 ** (attempt - 1)
          logger.warning("VLM request attempt %d of %d failed (%s); retrying in %.2f s",
                         attempt, self.max_retries, last_error, delay)
          time.sleep(delay)
    raise VLMError(f"VLM request to {self.url} failed after {self.max_retries} attempts; last "
                   f"error: {last_error}")

  def _decode(self, text: bytes) -> dict[str, Any]:
    """A response body -> its JSON object."""
    try:
      return json.loads(text)
    except ValueError:
      raise VLMError(f"VLM endpoint {self.url} returned invalid JSON: {text[:300]!r}") from None

  def _describe(self, error: Exception) -> str:
    """A failed request in words, the server's message included and the API key masked."""
    if isinstance(error, urllib.error.HTTPError):
      text = f"HTTP {error.code}: {_server_message(error)}"
    else:
      text = f"{type(error).__name__}: {error}"
    return text.replace(self.api_key, "***") if self.api_key else text

  def _sample(self, body: dict[str, Any]) -> list[str]:
    """``num_samples`` replies to ``body``, asking again for the rest when a server ignores
    ``n``."""
    replies: list[str] = []
    while len(replies) < self.num_samples:
      missing = self.num_samples - len(replies)
      replies.extend(_reply_texts(self._post({**body, "n": missing}))[:missing])
    return replies

  def judge(self, frames, task: str) -> Judgement:
    """Judge one rollout: frames ``[T, H, W, 3]`` (uint8 or [-1, 1] floats), its task."""
    return Judgement.from_replies(self._sample(self.request_body(frames, task)))

  def __call__(self, frames, task: str | Sequence[str]) -> np.ndarray:
    """Rewards of a batch: frames ``[B, T, H, W, 3]``, one task for all or ``B`` tasks ->
    float32 ``[B]`` (1 success, 0 failure, NaN unparsed). Videos are judged concurrently; any
    :class:`VLMError` propagates."""
    frames = np.asarray(frames)
    if frames.ndim != 5 or frames.shape[-1] != 3:
      raise ValueError(f"expected frames [B, T, H, W, 3], got shape {frames.shape}")
    batch = frames.shape[0]
    if task is None:
      raise TypeError("expected a task description (str) or one per video, got None")
    tasks = [task] * batch if isinstance(task, str) else list(task)
    if len(tasks) != batch:
      raise ValueError(f"expected one task or {batch} tasks (one per video), got {task!r}")
    workers = min(self.max_workers, max(batch, 1))
    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
      judgements = list(pool.map(self.judge, frames, tasks))
    return np.array([j.reward for j in judgements], np.float32)
