"""What the loop fits and scores, and how a sensor effect remakes it from the recording.

``Observations``: the observed frames (stage 1) from the lifted one on and the lifted particles
(stage 2). The loop starts from the ones it is given; a sensor effect in the library (a camera
time offset) changes them, not the simulated motion.

``Reobserver``: stages 1-2 of a recording, re-run with some cameras shifted by whole frames
or with another floor (``observe``). A camera that shows the scene ``k`` frames late or early
has its frame taken from the set ``k`` frames away, so that every camera of a set shows the
same instant again; a set whose shifted frame lies outside the recording is left out (so a
leading camera costs the first frame, a lagging one the last). The floor bounds the carving
from below (nothing below a declared floor is kept, since no camera sees under an object): a
floor the loop finds tilted must cut the observations where it lies, not where it was declared.
The first complete set is lifted again, and the surface tracks are made again. Results are
cached per shift and floor.

What it is for: the loop closure's candidates that change the observations (``loop.library``:
a camera time offset, a tilted floor). Without a recording (identify_node works on topics, not
on a bag) there is no ``Reobserver``: sensor effects are not tried, and a tilted floor is
fitted on the observations as they were cut.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from mosiv_ros.io.recording import FrameSet, Recording, match_frames
from mosiv_ros.io.scene import DeclaredGround
from mosiv_ros.lifting.lift import LiftedParticles, lift_first_complete
from mosiv_ros.prepare import RunConfig
from mosiv_ros.recon.reconstruct import ObservedFrame, Reconstructor
from mosiv_ros.recon.tracks import SurfaceTracker


@dataclass
class Observations:
    """Observed frames from the lifted one on, in stamp order, and the lifted particles."""

    frames: list[ObservedFrame]
    lifted: LiftedParticles


class Reobserver:
    """Stages 1-2 of ``recording`` with ``config``'s reconstruction and lifting settings."""

    def __init__(self, recording: Recording, config: RunConfig) -> None:
        self.recording, self.config = recording, config
        self.sets = match_frames(recording.cameras, int(round(config.reconstruction.sync_tolerance * 1e9)))
        self._cache: dict[tuple, Observations] = {}

    @property
    def cameras(self) -> list[str]:
        return sorted(self.recording.cameras)

    def observe(self, shifts: dict[str, int] | None = None, ground: DeclaredGround | None = None) -> Observations:
        """Stages 1-2 with camera ``c``'s frames taken ``shifts[c]`` sets earlier, and ``ground``.

        A camera showing the scene at t + k frames (it leads by k) is read from the set k
        earlier: ``shifts[c] = k``. ``ground`` (default: the recording's declared one) is the
        floor below which nothing is kept.
        """
        shifted = tuple(sorted((c, int(k)) for c, k in (shifts or {}).items() if k))
        key = (shifted, None if ground is None else (ground.height, ground.normal))
        if key not in self._cache:
            scene = self.recording.scene
            if ground is not None:
                scene = replace(scene, ground=ground)
            reconstructor = Reconstructor(self.recording.cameras, self.config.reconstruction, scene,
                                          SurfaceTracker(self.config.reconstruction.tracks))
            frames = [reconstructor.reconstruct(s) for s in self._shifted(dict(shifted))]
            lifted = lift_first_complete(frames, self.config.lifting, scene)
            self._cache[key] = Observations([f for f in frames if f.stamp_ns >= lifted.stamp_ns], lifted)
        return self._cache[key]

    def _shifted(self, shifts: dict[str, int]) -> list[FrameSet]:
        out = []
        for index, frame_set in enumerate(self.sets):
            frames = dict(frame_set.frames)
            for camera, k in shifts.items():
                source = index - k
                if not 0 <= source < len(self.sets) or camera not in self.sets[source].frames:
                    break
                frames[camera] = self.sets[source].frames[camera]
            else:
                out.append(FrameSet(frame_set.stamp_ns, frames))
        return out
