"""The wire messages under threads: one station process serves many robots, each on its own thread."""

_THREADS_DECODE = """
import sys, threading
sys.setswitchinterval(0.0005)
from bridge.core import wire as M
kinds = M._every_message_type()
data = M.encode(M.LearnerState(stamp=1.0, seq=1, x=0.0, y=0.0, theta=0.0))
go = threading.Event()
def work(i):
    go.wait()
    for _ in range(200):
        for k in kinds[i % len(kinds):] + kinds[:i % len(kinds)]:
            try:
                M.decode(data, k)
            except M.MessageError:
                pass
threads = [threading.Thread(target=work, args=(i,)) for i in range(16)]
[t.start() for t in threads]
go.set()
[t.join() for t in threads]
"""


def test_sixteen_threads_decode_every_message_type_at_once_without_crashing() -> None:
    """Finding (``bench fleet``, 16 robots in one station process): a station died of SIGSEGV in ``decode``. Each
    robot's thread built msgspec decoders on first use, and msgspec building a Decoder while another thread decodes
    crashes the process (this script without the fix: 2 crashes in 12 runs). Every message type's decoder is now
    built at import."""
    import subprocess
    import sys

    from bridge.core import wire as M

    assert set(M._every_message_type()) <= set(M._decoders)
    for _ in range(3):
        res = subprocess.run([sys.executable, "-c", _THREADS_DECODE], capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, (res.returncode, res.stderr[-2000:])
