"""The client side of a session's WebSocket (GET /sessions/{id}/stream): ``DenoiserClient.open_stream`` returns one.

    with client.open_stream(session.id, dtype="float16") as stream:
        for frame in frames:                      # client.frames.Frame (or a model FrameBundle)
            image, info = stream.send(frame)      # (H*s, W*s, 3) float32, FrameInfo as send_frame gives it
        image, info = stream.send_arrays(color=..., albedo=..., normal=..., depth=..., motion=..., jitter=...)

``send`` returns once the frame's output has arrived; ``send_many(frames, in_flight=2)`` keeps the next frame
travelling while the server steps the one before (outputs still in order). A frame the session refuses
raises ApiClientError (with the status the REST API gives the same error, its code and message) and the stream
stays usable; an error that ends the stream (the session is gone, the API key or owner token is wrong) raises
ApiClientError too and closes it. Built on ``websockets.sync.client``; messages are packed and unpacked by
client.codec (NumPy only), which the server imports too.
"""

from __future__ import annotations

import json
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from contextlib import suppress
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx

from client.answers import FrameResult
from client.rest import API_KEY_HEADER, ApiClientError, FrameInfo, ServerUnreachable

if TYPE_CHECKING:
    import numpy as np

    from client.frames import Frame

STREAM_PATH = "/sessions/{session_id}/stream"
# A close code 4000 + status carries the REST API's status for the error that ended the stream.
APPLICATION_CLOSE_CODES = range(4000, 5000)
MESSAGE_TOO_BIG = 1009
# Statuses of the errors that end a stream (its close codes are 4000 + status): nothing more is answered on it.
_STREAM_ENDING = frozenset({401, 403, 404, 503})
STREAM_DTYPES = ("float16", "float32")  # client.codec.DTYPES, named here so opening a stream needs no NumPy


def websocket_url(http_url: str, path: str) -> str:
    """ws:// or wss:// for the http:// or https:// base ``http_url``, plus ``path``."""
    if http_url.startswith("https://"):
        return "wss://" + http_url[len("https://"):] + path
    if http_url.startswith("http://"):
        return "ws://" + http_url[len("http://"):] + path
    raise ValueError(f"the service URL {http_url!r} is neither http:// nor https://")


class SessionStream:
    """One open WebSocket to a session (see the module notes). ``dtype``: what frames are sent in (float16 halves
    the bytes; the server rounds nothing else), ``output_dtype``: what the outputs come back in, ``buffers``: the
    buffers of a FrameBundle to send (the session's method's, as GET /sessions/{id} names them in model.buffers;
    None: every buffer the frame has)."""

    def __init__(self, base_url: str, session_id: str, headers: dict[str, str], *, dtype: str = "float32",
                 output_dtype: str = "float32", timeout: float = 60.0,
                 buffers: list[str] | tuple[str, ...] | None = None) -> None:
        from websockets.exceptions import InvalidHandshake, InvalidStatus
        from websockets.sync.client import connect

        for name, value in (("dtype", dtype), ("output_dtype", output_dtype)):
            if value not in STREAM_DTYPES:
                raise ValueError(f"{name} must be one of {', '.join(STREAM_DTYPES)}, got {value!r}")
        self.session_id = session_id
        self.dtype = dtype
        self.output_dtype = output_dtype
        self.buffers = None if buffers is None else tuple(buffers)
        self.url = websocket_url(base_url, STREAM_PATH.format(session_id=session_id))
        self._base_url = base_url
        try:
            # No per-message compression: float frames barely compress and deflate would cost more than the step.
            # Entered here, closed by close(): the connection outlives this call (websockets wants connect() used
            # as a context manager).
            self._socket = connect(self.url, additional_headers=headers, max_size=None, compression=None,
                                   open_timeout=timeout, close_timeout=timeout, ping_interval=None).__enter__()
        except InvalidStatus as error:  # answered over HTTP instead of upgrading (a proxy, an old server)
            response = error.response
            raise ApiClientError(response.status_code, "websocket_refused",
                                 f"{self.url}: the server answered {response.status_code} instead of opening the "
                                 f"WebSocket: {bytes(response.body or b'')[:200]!r}") from None
        except (OSError, TimeoutError, InvalidHandshake) as error:
            raise ServerUnreachable(self.url, str(error) or type(error).__name__) from error
        self._timeout = timeout

    def send(self, frame: Frame | bytes, frame_index: int | None | bool = True) -> FrameResult:
        """Denoise one frame: a client.frames.Frame or a model FrameBundle (sent in ``dtype``; ``frame_index`` True
        sends its own index, None leaves it to the session) or a message packed already (client.codec.encode_frame).
        Returns a FrameResult: the (H, W, 3) float32 output and its FrameInfo (round trip: from sending until the
        output was read)."""
        return self._answer(self._send(self._message(frame, frame_index)))

    def send_many(self, frames: Iterable[Frame | bytes], in_flight: int = 2,
                  frame_index: int | None | bool = True) -> Iterator[FrameResult]:
        """Denoise frames in order, keeping up to ``in_flight`` of them sent ahead of their outputs. The server
        answers a stream's frames in order, one at a time, so frame N+1 travels and is read while frame N steps.
        Yields each frame's FrameResult in order (its round trip runs from its sending until its output was read,
        so it includes waiting behind the frames before it). A frame the session refuses raises ApiClientError
        after the frames before it were yielded; the frames sent after it are answered and dropped first (the
        session has stepped them), so the stream stays usable."""
        if in_flight < 1:
            raise ValueError(f"in_flight must be at least 1, got {in_flight}")
        frames = iter(frames)
        sent: deque[float] = deque()
        more = True
        while True:
            while more and len(sent) < in_flight:
                frame = next(frames, None)
                more = frame is not None
                if more:
                    sent.append(self._send(self._message(frame, frame_index)))
            if not sent:
                return
            try:
                result = self._answer(sent.popleft())
            except ApiClientError as error:
                if error.status not in _STREAM_ENDING:
                    for started in sent:  # read their answers, so that the next send reads its own
                        with suppress(ApiClientError):
                            self._answer(started)
                raise
            yield result

    def _message(self, frame: Frame | bytes, frame_index: int | None | bool) -> bytes:
        from client.codec import encode_bundle

        if isinstance(frame, (bytes, bytearray, memoryview)):
            return frame
        return encode_bundle(frame, dtype=self.dtype, output_dtype=self.output_dtype, frame_index=frame_index,
                             buffers=self.buffers)

    def _send(self, data: bytes) -> float:
        """Send one frame message; returns when it was sent (perf_counter)."""
        from websockets.exceptions import ConnectionClosed

        started = time.perf_counter()
        try:
            self._socket.send(data)
        except ConnectionClosed as error:
            raise _closed_error(error) from None
        return started

    def _answer(self, started: float) -> FrameResult:
        """The next answer: the output of the frame sent at ``started``, or the error it was refused with."""
        from websockets.exceptions import ConnectionClosed

        from client.codec import decode_output

        try:
            answer = self._socket.recv(timeout=self._timeout)
        except ConnectionClosed as error:
            raise _closed_error(error) from None
        except TimeoutError:
            raise ServerUnreachable(self.url, f"no answer to the frame within {self._timeout:g} s") from None
        round_trip_ms = (time.perf_counter() - started) * 1000.0
        if isinstance(answer, str):
            raise _answer_error(answer)
        output = decode_output(answer)
        return FrameResult(output.image, _frame_info(output.header, round_trip_ms))

    def send_arrays(self, *, color: np.ndarray, albedo: np.ndarray, normal: np.ndarray, depth: np.ndarray,
                    motion: np.ndarray, jitter: tuple[float, float] = (0.0, 0.0), frame_index: int | None = None,
                    camera_cut: bool = False, **optional: np.ndarray) -> FrameResult:
        """``DenoiserClient.send_arrays`` over this WebSocket: a renderer's arrays, packed as they are (no EXR)."""
        from client.frames import make_frame

        frame = make_frame(color=color, albedo=albedo, normal=normal, depth=depth, motion=motion, jitter=jitter,
                           frame_index=frame_index, camera_cut=camera_cut, **optional)
        return self.send(frame, frame_index=frame_index)

    def close(self) -> None:
        self._socket.close()

    def __enter__(self) -> SessionStream:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def _frame_info(header: dict[str, Any], round_trip_ms: float) -> FrameInfo:
    """The output header as the POST route's X-* headers say it, so both transports give the same FrameInfo."""
    names = {"frame_index": "X-Frame-Index", "history": "X-History", "inference_ms": "X-Inference-Ms",
             "server_ms": "X-Server-Ms", "sanitized_pixels": "X-Sanitized-Pixels", "sanitized": "X-Sanitized",
             "repairs": "X-Repairs"}
    headers = httpx.Headers({name: str(header[field]) for field, name in names.items()
                             if header.get(field) is not None})
    return FrameInfo(frame_index=header.get("frame_index"), inference_ms=header.get("inference_ms"),
                     server_ms=header.get("server_ms"), history=header.get("history"), round_trip_ms=round_trip_ms,
                     sanitized_pixels=header.get("sanitized_pixels"), headers=headers)


def _answer_error(text: str) -> ApiClientError:
    """A text answer: the server refused the frame ({"error": {...}, "status", "frame_index"})."""
    try:
        body = json.loads(text)
        error = body["error"]
        return ApiClientError(int(body.get("status", 400)), error["code"], error["message"], error.get("details"))
    except (ValueError, KeyError, TypeError):
        return ApiClientError(502, "invalid_response", f"the server answered a frame with {text[:200]!r}")


def _closed_error(error) -> ApiClientError:
    """The stream ended: ApiClientError with the REST API's status where the close code carries one."""
    close = error.rcvd
    if close is None:
        return ApiClientError(502, "connection_lost", f"the stream ended without a close frame: {error}")
    code, _, message = close.reason.partition(": ")
    if close.code in APPLICATION_CLOSE_CODES:
        return ApiClientError(close.code - 4000, code, message or close.reason)
    if close.code == MESSAGE_TOO_BIG:
        return ApiClientError(413, "payload_too_large", f"the frame is larger than the server's WebSocket message "
                                                        f"limit ({close.reason or 'close code 1009'})")
    return ApiClientError(502, "stream_closed", f"the server closed the stream (code {close.code}): {close.reason}")


def file_sender(stream: SessionStream, bundles: bool,
                layout: str | dict | None) -> Callable[[Iterable[Path]], Iterator[tuple[bytes, FrameInfo]]]:
    """For DenoiserClient.stream_sequence: frame files -> (each output as a float32 RGB EXR, its FrameInfo), in
    order, the next file read and sent while the frame before it steps (``send_many``). Frame bundle files
    (``bundles``) are read as they are (the session repairs NaN / Inf; client.frames), a renderer's files in
    ``layout`` (default denoiser) in live mode, as the session would read them; a file without a frame index
    leaves it to the session.

    A layout other than ``denoiser`` is read by the model library's layout readers (model.layouts: NumPy and
    OpenEXR, never torch; tests/test_layers.py proves it), the one part of the model library the client imports:
    every renderer's channel names and conventions are known there once. Frame bundles need no model import."""
    from client.frames import encode_image_exr, read_frame_exr

    if bundles or layout in (None, "denoiser"):
        def read(path: Path):
            frame = read_frame_exr(path)
            return frame, bundles or frame.frame_index is not None
    else:
        from model.layouts import layout_from_value, read_layout_frame

        reader = layout_from_value(layout)

        def read(path: Path):
            result = read_layout_frame(path, reader, mode="live")
            return result.frame, result.frame_index_given

    def send_all(paths: Iterable[Path]) -> Iterator[tuple[bytes, FrameInfo]]:
        sent: deque = deque()  # the frames sent and not answered yet, oldest first

        def messages() -> Iterator[bytes]:
            for path in paths:
                frame, given = read(path)
                sent.append(frame)
                yield stream._message(frame, True if given else None)

        for image, info in stream.send_many(messages()):
            frame = sent.popleft()
            attributes = {"frame_index": info.frame_index, "sequence": frame.sequence,
                          "scale": image.shape[0] // frame.height}
            yield encode_image_exr(image, {key: value for key, value in attributes.items() if value is not None}), info

    return send_all
