"""The two phantom renderers every images-only identification and diagnosis test runs on (docs/design.md, "Images that
calfit did not make"): calfit's first phantom (`CalfPhantom`: an egg-shaped calf, k-space band-limited T1 images)
and the second, drawn independently (`MRIPhantom`: its own outline and anatomy, fat septa, muscle streaks, partial
volume by box-averaging, its own coil bias). A method shown on one renderer only is not shown."""

from orchestrator.phantom import CalfPhantom, MRIPhantom

RENDERERS = {"calf": CalfPhantom, "mri": lambda: MRIPhantom.at_resolution(0.36)}


def phantom(renderer: str):
    """A new phantom of the named renderer, at 0.36 mm pixels over a ~150 mm field of view."""
    return RENDERERS[renderer]()
