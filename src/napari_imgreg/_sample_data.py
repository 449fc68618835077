"""napari sample data: the generated outcrop model and a photo with its prior render.

The scene is generated once (a few seconds) and cached; see
:func:`napari_imgreg.sample.sample_scene`.
"""

from __future__ import annotations

from .widgets._layers import surface_layer_data

__all__ = ["sample_outcrop_model", "sample_outcrop_photo"]


def _sample_scene():
    from .sample import sample_scene
    from .scene import Scene

    folder = sample_scene("small")
    return folder, Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")


def sample_outcrop_model() -> list:
    """The sample outcrop as a textured Surface layer (view it in 3D)."""
    _, scene = _sample_scene()
    return [surface_layer_data(scene, name="sample outcrop")]


def sample_outcrop_photo() -> list:
    """The first sample photo and the render from its sensor prior.

    The render sits on top at half opacity, so the prior's misfit shows.
    """
    from .io.photos import load_photo
    from .prior import prior_for_photo
    from .render import render

    folder, scene = _sample_scene()
    photo_path = sorted(folder.glob("IMG_*.jpg"))[0]
    photo = load_photo(photo_path)
    prior = prior_for_photo(photo, scene)
    result = render(scene, prior.intrinsics, prior.pose)
    meta = {"photo_path": str(photo_path), "intrinsics": prior.intrinsics.to_dict(),
            "pose": prior.pose.to_dict(), "assumptions": prior.assumptions}
    return [
        (photo.image, {"name": photo_path.stem, "rgb": True, "metadata": meta}, "image"),
        (
            result.rgb,
            {"name": f"{photo_path.stem} prior render", "rgb": True, "opacity": 0.5,
             "metadata": meta},
            "image",
        ),
    ]
