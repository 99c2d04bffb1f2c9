"""The peer benchmark's lockstep (benchmarks/identify_peers.py with benchmarks/peers/run_peers.py): starenv and the
peer time their sets in turns that never overlap, whatever the number of sets a turn."""

import importlib.util
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("identify_peers", ROOT / "benchmarks" / "identify_peers.py")
identify_peers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(identify_peers)

# A stand-in for run_peers.py: it paces itself with run_peers.Lockstep, as the tetra3rs timing does, and writes the
# moment it takes each set.
FAKE_PEER = textwrap.dedent(f"""
    import importlib.util, json, sys, time
    import numpy as np
    spec = importlib.util.spec_from_file_location("run_peers", {str(ROOT / "benchmarks" / "peers" / "run_peers.py")!r})
    run_peers = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(run_peers)
    count = len(np.load(sys.argv[1])["sizes"])
    lockstep = run_peers.Lockstep(int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6]))
    lockstep.ready()
    stamps = []
    for k in range(count):
        lockstep.before(k)
        stamps.append(time.monotonic_ns())
        time.sleep(0.0005)
    lockstep.end(count)
    json.dump(stamps, open(sys.argv[2], "w"))
""")


class _Clock:
    """An identifier that notes the moment of each call and labels nothing."""

    def __init__(self):
        self.stamps = []

    def identify(self, stars, cameras, prior=None):
        self.stamps.append(time.monotonic_ns())
        time.sleep(0.0005)
        return [identify_peers.StarMeasurements(stars[0].xy)]


@pytest.mark.parametrize("count, chunk", [(25, 10), (20, 10), (7, 3), (4, 1)])
def test_the_two_sides_take_turns_and_every_set_is_timed(tmp_path, count, chunk):
    # The turns must alternate: all of starenv's sets of turn t before all of the peer's, and those before starenv's
    # turn t + 1; a last turn of fewer sets (25 by 10) and an exact one (20 by 10) both end without a hang.
    runner = tmp_path / "fake_peer.py"
    runner.write_text(FAKE_PEER)
    sets = {"sizes": np.ones(count, dtype=int)}
    stars = [identify_peers.StarMeasurements(np.zeros((1, 2))) for _ in range(count)]
    clock = _Clock()
    with identify_peers.PeerRun(sets, chunk, runner=[sys.executable, str(runner)]) as peers:
        peers.ready()
        rows = identify_peers.timed_rows(clock, None, stars, [np.zeros(1, dtype=int)] * count, [None] * count,
                                         after_chunk=peers.chunk, chunk=chunk)
        peer_stamps = peers.results()
    ours = clock.stamps[1:]  # (the first call is the untimed warm-up)
    assert len(rows) == len(ours) == len(peer_stamps) == count
    for first in range(0, count, chunk):
        turn, following = slice(first, first + chunk), slice(first + chunk, first + 2 * chunk)
        assert max(ours[turn]) < min(peer_stamps[turn])
        if first + chunk < count:
            assert max(peer_stamps[turn]) < min(ours[following])
