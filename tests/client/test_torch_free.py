"""The client without torch or the model library: a renderer plug-in's install (httpx, numpy, OpenEXR).

Each test runs a script in a subprocess whose imports of ``torch`` and ``model`` raise ImportError, so a stray
import anywhere on the path fails it."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BLOCKER = '''
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('torch', 'model'):
            raise ImportError(f'blocked: {name}')
sys.meta_path.insert(0, Block())
'''
# Frames of a 4x6 render: color grows with the frame index, so every output is known (the fakes halve the color).
FRAMES = '''
import json
import numpy as np
from client.frames import make_frame, encode_frame_exr, frame_file_name
def arrays(index):
    h, w = 4, 6
    normal = np.zeros((h, w, 3), np.float32); normal[..., 2] = 1
    return dict(color=np.full((h, w, 3), 0.25 * (index + 1), np.float32), albedo=np.full((h, w, 3), 0.5, np.float32),
                normal=normal, depth=np.ones((h, w), np.float32), motion=np.zeros((h, w, 2), np.float32),
                jitter=(0.125, -0.25))
'''


def run_blocked(script: str, tmp_path: Path) -> str:
    code = BLOCKER + FRAMES + textwrap.dedent(script)
    result = subprocess.run([sys.executable, "-c", code, str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


def test_frames_stream_over_http_from_a_folder_and_from_arrays(tmp_path):
    out = run_blocked('''
        from pathlib import Path
        from tests.client.fake_api import FakeApi
        root = Path(sys.argv[1])
        sequence = root / "seq"; sequence.mkdir()
        for index in range(3):
            (sequence / frame_file_name(index)).write_bytes(
                encode_frame_exr(make_frame(**arrays(index), frame_index=index, sequence="seq")))
        (sequence / "manifest.json").write_text(json.dumps({
            "format": "denoiser-sequence/1", "sequence": "seq", "scene": None, "width": 6, "height": 4, "scales": [],
            "frames": [{"index": i, "file": frame_file_name(i), "camera_cut": False} for i in range(3)]}))
        with FakeApi().client() as client:
            session = client.create_session("wskpn-xs", alias="champion")
            summary = client.stream_sequence(session.id, sequence, root / "out", png=True)
            assert [info.history for info in summary.frames] == ["started", "continued", "continued"]
            from client.frames import decode_image_exr
            last = decode_image_exr((root / "out" / "frame_0002.exr").read_bytes())
            assert np.allclose(last, 0.375), last.mean()
            assert [p.name for p in summary.pngs] == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
            image, info = client.send_arrays(session.id, **arrays(3))  # the session numbers it: frame 3
            assert info.frame_index == 3 and info.history == "continued" and np.allclose(image, 0.5)
            assert session["id"] == session.id and session.model.version == "1"
        assert not [m for m in sys.modules if m.split(".")[0] in ("torch", "model")]
        print("ok")
    ''', tmp_path)
    assert out.strip() == "ok"


def test_frames_stream_over_the_websocket_with_the_codec(tmp_path):
    out = run_blocked('''
        import threading
        from websockets.sync.server import serve
        from client.codec import decode_frame, encode_output
        from client.stream import SessionStream
        def handler(socket):  # a stand-in session: half the color, numbered as sent
            for message in socket:
                frame = decode_frame(message)
                socket.send(encode_output(np.ascontiguousarray(frame.hwc("color")) * 0.5,
                                          frame_index=frame.frame_index if frame.frame_index is not None else 7,
                                          history="continued"))
        with serve(handler, "127.0.0.1", 0) as server:
            threading.Thread(target=server.serve_forever, daemon=True).start()
            port = server.socket.getsockname()[1]
            with SessionStream(f"http://127.0.0.1:{port}", "s1", {}, dtype="float16") as stream:
                image, info = stream.send_arrays(**arrays(1), frame_index=4)
                assert info.frame_index == 4 and image.shape == (4, 6, 3) and np.allclose(image, 0.25)
                image, info = stream.send(make_frame(**arrays(0)), frame_index=None)
                assert info.frame_index == 7 and np.allclose(image, 0.125)
                assert info.headers["X-History"] == "continued"
            server.shutdown()
        assert not [m for m in sys.modules if m.split(".")[0] in ("torch", "model")]
        print("ok")
    ''', tmp_path)
    assert out.strip() == "ok"
