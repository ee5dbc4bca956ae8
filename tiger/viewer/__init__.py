"""``tiger view``: a web viewer (viser) drawn by TIGER's rasterizer, to look, ask, select, edit and delete.

``serve(scene)`` blocks until Ctrl-C; ``serve(scene, block=False)`` returns the running
:class:`ViewerServer` (for notebooks; call ``.stop()``). viser is an optional dependency
(``pip install viser``, the ``viewer`` extra).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import torch

from tiger.retrieval.text import TextEncoder
from tiger.render import Camera
from tiger.scene import GaussianScene

from .state import Selection, ViewerError, ViewerState

__all__ = ["serve", "ViewerState", "ViewerError", "Selection"]


def serve(scene: GaussianScene, *, encoder: Optional[TextEncoder] = None, host: str = "127.0.0.1",
          port: int = 8080, cameras: Optional[list[Camera]] = None, out_dir: Union[str, Path] = "outputs/view",
          models: Optional[str] = None, device: Optional[Union[str, torch.device]] = None,
          encoder_note: str = "", block: bool = True):
    """Serve ``scene`` in the browser at ``http://host:port``.

    Args:
        scene: the scene (with ``lang`` to ask, select, edit and delete); moved to ``device``.
        encoder: text encoder for the queries (``encode_text``); None disables text queries
            (the point prompt still works).
        cameras: capture cameras for the camera list (e.g. ``read_cameras_json``).
        out_dir: where Save writes PLYs (never a path from the page).
        models: model folder/config for the diffusion guidances.
        block: serve until Ctrl-C (True) or return the running server.
    """
    from tiger.utils.lazy import require

    require("viser", "viser==1.1.1", purpose="tiger view; or the viewer extra")
    from .server import ViewerServer

    dev = torch.device(device) if device is not None else scene.device
    state = ViewerState(scene.to(dev), encoder, encoder_note=encoder_note or (
        "" if encoder is not None else "no text encoder (pass --text-embeddings or CLIP weights via --models): "
        "text queries are off; the point prompt works"), out_dir=out_dir, models=models, cameras=cameras)
    server = ViewerServer(state, host, port, device=dev)
    try:
        server.start()
    except KeyboardInterrupt:  # Ctrl-C while starting: stop what started
        server.stop()
        return server
    if block:
        server.serve_forever()
    return server
