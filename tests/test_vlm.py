"""The VLM success judge against a scripted local chat-completions server: answer parsing, frame
subsampling, the request it sends, majority votes, retries and errors, servers that ignore ``n``,
batched rewards and configuration from the environment."""

import base64
import dataclasses
import http.server
import io
import json
import logging
import math
import socket
import threading
import time
from typing import Any, Callable

import numpy as np
import pytest
from PIL import Image

from wmjax.eval import vlm

pytestmark = pytest.mark.unit

KEY = "sk-test-secret-0123456789"


@dataclasses.dataclass
class Reply:
  """What the fake server answers: an HTTP status, a JSON payload, after ``delay`` seconds."""

  payload: Any
  status: int = 200
  delay: float = 0.0


def completion(*texts: str) -> dict:
  return {"object": "chat.completion",
          "choices": [{"index": i, "message": {"role": "assistant", "content": text},
                       "finish_reason": "stop"} for i, text in enumerate(texts)]}


def prompt_text(body: dict) -> str:
  return body["messages"][0]["content"][0]["text"]


def images(body: dict) -> list[np.ndarray]:
  """The frames of a request, decoded from their PNG data URLs."""
  frames = []
  for part in body["messages"][0]["content"][1:]:
    assert part["type"] == "image_url"
    header, data = part["image_url"]["url"].split(",", 1)
    assert header == "data:image/png;base64"
    frames.append(np.asarray(Image.open(io.BytesIO(base64.b64decode(data)))))
  return frames


class FakeVLM:
  """A scripted OpenAI-compatible server: ``respond(body) -> Reply`` (default: one choice per
  request saying yes); every request is recorded as ``{"path", "headers", "body"}``."""

  def __init__(self):
    self.requests: list[dict] = []
    self.lock = threading.Lock()
    self.respond: Callable[[dict], Reply] = lambda body: Reply(completion("Answer: Yes"))

  def script(self, *replies: Reply) -> None:
    """Answer the next requests with ``replies`` in order."""
    queue = list(replies)
    self.respond = lambda body: queue.pop(0)

  @property
  def bodies(self) -> list[dict]:
    return [request["body"] for request in self.requests]


class _Handler(http.server.BaseHTTPRequestHandler):

  def do_POST(self):
    fake = self.server.fake
    body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
    headers = {name.lower(): value for name, value in self.headers.items()}
    with fake.lock:
      fake.requests.append({"path": self.path, "headers": headers, "body": body})
      reply = (fake.respond(body) if self.path == "/v1/chat/completions"
               else Reply({"error": {"message": "not found"}}, 404))
    time.sleep(reply.delay)
    data = json.dumps(reply.payload).encode()
    self.send_response(reply.status)
    self.send_header("Content-Type", "application/json")
    self.send_header("Content-Length", str(len(data)))
    self.end_headers()
    self.wfile.write(data)

  def log_message(self, *args):
    pass


class _Server(http.server.ThreadingHTTPServer):

  def handle_error(self, request, client_address):
    pass  # a client that timed out closed its socket before a delayed reply


@pytest.fixture
def server():
  httpd = _Server(("127.0.0.1", 0), _Handler)
  httpd.fake = FakeVLM()
  httpd.fake.url = f"http://127.0.0.1:{httpd.server_address[1]}/v1/"
  thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.02},
                            daemon=True)
  thread.start()
  yield httpd.fake
  httpd.shutdown()
  httpd.server_close()
  thread.join()


def make_judge(server, **kwargs) -> vlm.VLMJudge:
  return vlm.VLMJudge(**{"base_url": server.url, "model": "test-vlm", "backoff": 0.01, **kwargs})


def video(length=20, size=8, seed=0) -> np.ndarray:
  return np.random.default_rng(seed).integers(0, 256, (length, size, size, 3), dtype=np.uint8)


# ----------------------------------------------------------------------------- parsing


@pytest.mark.parametrize("text, expected", [
    ("The gripper grasps the cup and lifts it. Answer: Yes", True),
    ("The cup is never touched.\nAnswer: No", False),
    ("**Answer:** Yes", True),
    ("**Answer: No**", False),
    ("answer: yes.", True),
    ("ANSWER - No", False),
    ("Final answer: **yes**", True),
    ("Answer: 'No'.", False),
    ("Yes, the robot reaches the drawer, yes it pulls, but it never opens it.\n\nAnswer: No",
     False),
    ("First I thought Answer: Yes, but looking again at the last frame... Answer: No", False),
    ("Answer: No. On reflection the answer is clear.", False),
    ("I am not sure.", None),
    ("", None),
    (None, None),
    ("Answer: maybe", None),
    ("Answer: Yesterday the robot", None),
    ("Yes", None),
    ("The answer is no", None),
])
def test_parse_answer(text, expected):
  assert vlm.parse_answer(text) is expected


def test_wpe_prompt_is_the_papers():
  assert vlm.WPE_PROMPT.startswith("Here is a sequence of frames from a policy rollout video.")
  assert "output Answer: Yes or Answer: No'. Task: {task_description} Note:" in vlm.WPE_PROMPT
  assert vlm.WPE_PROMPT.endswith("places it in the basket would be considered a success.")
  assert vlm.WPE_PROMPT.count("{") == 1 and vlm.WPE_PROMPT.count("}") == 1


# ----------------------------------------------------------------------------- frames


def test_subsample_frames_keeps_first_and_last_evenly_spaced():
  frames = video(20)
  np.testing.assert_array_equal(vlm.subsample_frames(frames, 5), frames[[0, 5, 10, 14, 19]])
  np.testing.assert_array_equal(vlm.subsample_frames(frames, 19), frames[np.r_[0:9, 10:20]])
  np.testing.assert_array_equal(vlm.subsample_frames(frames, 1), frames[-1:])
  np.testing.assert_array_equal(vlm.subsample_frames(frames[:3], 8), frames[:3])  # T <= count


def test_subsample_frames_converts_floats_and_validates():
  floats = np.stack([np.full((2, 2, 3), v, np.float32) for v in (-1.0, 0.0, 1.0)])
  out = vlm.subsample_frames(floats, 3)
  assert out.dtype == np.uint8
  np.testing.assert_array_equal(out[:, 0, 0, 0], [0, 128, 255])
  with pytest.raises(ValueError, match=r"\[T, H, W, 3\]"):
    vlm.subsample_frames(np.zeros((4, 8, 8)), 2)
  with pytest.raises(ValueError, match=r"\[T, H, W, 3\]"):
    vlm.subsample_frames(np.zeros((0, 8, 8, 3)), 2)
  with pytest.raises(ValueError, match="count >= 1"):
    vlm.subsample_frames(video(), 0)


# ----------------------------------------------------------------------------- the request


def test_request_sends_prompt_frames_and_key(server):
  judge = make_judge(server, api_key=KEY, num_frames=5, num_samples=3, temperature=0.5,
                     max_tokens=64)
  server.respond = lambda body: Reply(completion(*["Answer: Yes"] * body["n"]))
  frames = video(20)
  judge.judge(frames, "open the top drawer")

  (request,) = server.requests
  assert request["path"] == "/v1/chat/completions"
  assert request["headers"]["authorization"] == f"Bearer {KEY}"
  assert request["headers"]["content-type"] == "application/json"
  body = request["body"]
  assert (body["model"], body["n"], body["temperature"], body["max_tokens"]) == (
      "test-vlm", 3, 0.5, 64)
  (message,) = body["messages"]
  assert message["role"] == "user"
  assert prompt_text(body) == vlm.WPE_PROMPT.replace("{task_description}", "open the top drawer")
  assert "Task: open the top drawer Note:" in prompt_text(body)
  assert all(part["image_url"]["detail"] == "low" for part in message["content"][1:])
  sent = images(body)
  assert len(sent) == 5
  np.testing.assert_array_equal(sent[0], frames[0])
  np.testing.assert_array_equal(sent[-1], frames[-1])
  np.testing.assert_array_equal(np.stack(sent), frames[[0, 5, 10, 14, 19]])
  assert KEY not in repr(judge)


def test_no_key_no_authorization_header(server):
  make_judge(server, num_samples=1, image_detail="high").judge(video(3), "wave")
  (request,) = server.requests
  assert "authorization" not in request["headers"]
  assert len(images(request["body"])) == 3  # fewer frames than num_frames: all of them
  assert request["body"]["messages"][0]["content"][1]["image_url"]["detail"] == "high"


# ----------------------------------------------------------------------------- votes


def test_majority_vote_counts_replies():
  replies = ["It lifts the cup. Answer: Yes", "**Answer:** no", "answer - yes."]
  judgement = vlm.Judgement.from_replies(replies)
  assert (judgement.success, judgement.yes, judgement.no, judgement.unparsed) == (True, 2, 1, 0)
  assert judgement.replies == tuple(replies)
  tie = vlm.Judgement.from_replies(["Answer: Yes", "Answer: No", "hmm"])
  assert (tie.success, tie.yes, tie.no, tie.unparsed, tie.reward) == (False, 1, 1, 1, 0.0)
  garbled = vlm.Judgement.from_replies(["I cannot tell", ""])
  assert garbled.success is None and garbled.unparsed == 2 and math.isnan(garbled.reward)


def test_judge_votes_over_n_choices(server):
  server.respond = lambda body: Reply(completion("Answer: No", "Answer: Yes", "Answer: Yes"))
  judgement = make_judge(server, num_samples=3).judge(video(), "pick up the cup")
  assert (judgement.success, judgement.yes, judgement.no, judgement.unparsed) == (True, 2, 1, 0)
  assert len(server.requests) == 1

  server.respond = lambda body: Reply(completion("Answer: No", "Answer: No", "Answer: Yes"))
  assert make_judge(server).judge(video(), "pick up the cup").success is False


def test_all_garbled_gives_none_and_nan(server):
  server.respond = lambda body: Reply(completion("I am not sure.", "Answer: maybe", ""))
  judge = make_judge(server)
  judgement = judge.judge(video(), "stack the blocks")
  assert judgement.success is None and judgement.unparsed == 3
  rewards = judge(video()[None], "stack the blocks")
  assert rewards.shape == (1,) and np.isnan(rewards[0])


@pytest.mark.parametrize("per_request, n_sent", [(1, [5, 4, 3, 2, 1]), (2, [5, 3, 1])])
def test_server_ignoring_n_is_asked_again(server, per_request, n_sent):
  server.respond = lambda body: Reply(completion(*["Answer: Yes"] * per_request))
  judgement = make_judge(server, num_samples=5).judge(video(), "push the block")
  assert [body["n"] for body in server.bodies] == n_sent
  assert len(server.requests) == math.ceil(5 / per_request)
  assert (judgement.yes, len(judgement.replies)) == (5, 5)


# ----------------------------------------------------------------------------- retries and errors


def test_timeout_is_retried(server, caplog):
  server.script(Reply(completion("Answer: No"), delay=1.0), Reply(completion("Answer: Yes")))
  judge = make_judge(server, api_key=KEY, num_samples=1, timeout=0.3)
  with caplog.at_level(logging.WARNING, logger=vlm.__name__):
    judgement = judge.judge(video(), "close the lid")
  assert judgement.success is True
  assert len(server.requests) == 2
  assert "attempt 1 of 3" in caplog.text and "timed out" in caplog.text
  assert KEY not in caplog.text


def test_timeouts_exhaust_retries(server):
  server.respond = lambda body: Reply(completion("Answer: Yes"), delay=1.0)
  judge = make_judge(server, num_samples=1, timeout=0.3, max_retries=3)
  with pytest.raises(vlm.VLMError, match="after 3 attempts") as error:
    judge.judge(video(), "close the lid")
  assert "timed out" in str(error.value)
  assert len(server.requests) == 3


@pytest.mark.parametrize("status", [500, 503, 429])
def test_server_errors_are_retried(server, status):
  server.script(Reply({"error": {"message": "overloaded"}}, status),
                Reply(completion("Answer: Yes")))
  assert make_judge(server, num_samples=1).judge(video(), "wipe the table").success is True
  assert len(server.requests) == 2


def test_persistent_server_error_raises_with_its_message(server):
  server.respond = lambda body: Reply({"error": {"message": "model is overloaded"}}, 502)
  with pytest.raises(vlm.VLMError) as error:
    make_judge(server, max_retries=2).judge(video(), "wipe the table")
  assert "after 2 attempts" in str(error.value)
  assert "HTTP 502: model is overloaded" in str(error.value)
  assert len(server.requests) == 2


def test_unauthorized_is_not_retried_and_hides_the_key(server, caplog):
  message = f"Incorrect API key provided: {KEY}."
  server.respond = lambda body: Reply({"error": {"message": message}}, 401)
  with caplog.at_level(logging.DEBUG, logger=vlm.__name__):
    with pytest.raises(vlm.VLMError) as error:
      make_judge(server, api_key=KEY).judge(video(), "open the drawer")
  assert len(server.requests) == 1
  assert "HTTP 401" in str(error.value) and "Incorrect API key provided" in str(error.value)
  assert KEY not in str(error.value) and KEY not in caplog.text


def test_connection_refused_is_retried():
  with socket.socket() as probe:  # a port with nothing listening
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
  judge = vlm.VLMJudge(f"http://127.0.0.1:{port}/v1", "test-vlm", max_retries=2, backoff=0.01)
  with pytest.raises(vlm.VLMError, match="after 2 attempts.*refused"):
    judge.judge(video(), "open the drawer")


def test_response_without_choices_raises(server):
  server.respond = lambda body: Reply({"choices": []})
  with pytest.raises(vlm.VLMError, match="'choices'"):
    make_judge(server).judge(video(), "open the drawer")


# ----------------------------------------------------------------------------- batches


def test_batched_call_returns_rewards_in_order(server):
  answers = {"open the drawer": "Answer: Yes", "close the drawer": "Answer: No",
             "wave": "I cannot see the robot."}

  def respond(body):
    task = next(task for task in answers if f"Task: {task} Note" in prompt_text(body))
    return Reply(completion(*[answers[task]] * body["n"]), delay=0.05)

  server.respond = respond
  judge = make_judge(server, max_workers=3)
  frames = np.stack([video(seed=i) for i in range(3)])
  rewards = judge(frames, ["open the drawer", "close the drawer", "wave"])
  assert rewards.dtype == np.float32 and rewards.shape == (3,)
  np.testing.assert_array_equal(rewards, [1.0, 0.0, np.nan])
  assert len(server.requests) == 3
  # the video reaches the server with the task it belongs to
  for body in server.bodies:
    index = list(answers).index(next(t for t in answers if f"Task: {t} Note" in prompt_text(body)))
    np.testing.assert_array_equal(images(body)[0], frames[index, 0])

  np.testing.assert_array_equal(judge(frames[:2], "close the drawer"), [0.0, 0.0])


def test_batched_call_takes_float_frames(server):
  frames = np.zeros((2, 4, 6, 6, 3), np.float32)
  np.testing.assert_array_equal(make_judge(server, num_samples=1)(frames, "wave"), [1.0, 1.0])
  assert images(server.bodies[0])[0].max() == 128  # 0.0 in [-1, 1] is mid grey


# ----------------------------------------------------------------------------- configuration


@pytest.mark.parametrize("kwargs, match", [
    ({"num_samples": 0}, "num_samples >= 1"),
    ({"num_frames": 0}, "num_frames >= 1"),
    ({"max_retries": 0}, "max_retries >= 1"),
    ({"timeout": 0.0}, "timeout > 0"),
    ({"image_detail": "medium"}, "image_detail"),
    ({"prompt": "Did the robot succeed?"}, "task_description"),
])
def test_invalid_settings_raise(kwargs, match):
  with pytest.raises(ValueError, match=match):
    vlm.VLMJudge("http://localhost/v1", "m", **kwargs)


def test_invalid_inputs_raise(server):
  judge = make_judge(server)
  with pytest.raises(ValueError, match=r"\[B, T, H, W, 3\]"):
    judge(video(), "wave")
  with pytest.raises(ValueError, match="2 tasks"):
    judge(np.stack([video(), video()]), ["wave"])
  with pytest.raises(TypeError, match="None"):
    judge(np.stack([video(), video()]), None)
  with pytest.raises(TypeError, match="str"):
    judge.judge(video(), 3)
  assert not server.requests


def test_from_env(monkeypatch):
  for name in ("WMJAX_VLM_BASE_URL", "WMJAX_VLM_MODEL", "WMJAX_VLM_API_KEY", "OPENAI_BASE_URL",
               "OPENAI_API_KEY", "MY_BASE_URL", "MY_MODEL", "MY_API_KEY"):
    monkeypatch.delenv(name, raising=False)
  judge = vlm.VLMJudge.from_env()
  assert (judge.base_url, judge.model, judge.api_key) == ("https://api.openai.com/v1", "gpt-4o",
                                                          None)

  monkeypatch.setenv("OPENAI_BASE_URL", "http://openai-compatible/v1")
  monkeypatch.setenv("OPENAI_API_KEY", "sk-openai")
  judge = vlm.VLMJudge.from_env(num_samples=5)
  assert (judge.base_url, judge.api_key, judge.num_samples) == (
      "http://openai-compatible/v1", "sk-openai", 5)

  monkeypatch.setenv("WMJAX_VLM_BASE_URL", "http://localhost:8000/v1")
  monkeypatch.setenv("WMJAX_VLM_MODEL", "Qwen/Qwen2.5-VL-7B-Instruct")
  monkeypatch.setenv("WMJAX_VLM_API_KEY", KEY)
  judge = vlm.VLMJudge.from_env(temperature=0.0)
  assert (judge.base_url, judge.model, judge.api_key, judge.temperature) == (
      "http://localhost:8000/v1", "Qwen/Qwen2.5-VL-7B-Instruct", KEY, 0.0)
  assert KEY not in repr(judge)

  monkeypatch.setenv("MY_MODEL", "llava")
  assert vlm.VLMJudge.from_env(prefix="MY_").model == "llava"
