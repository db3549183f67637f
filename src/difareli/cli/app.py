"""difareli-app: a local web page where a user drops a face photo (or picks a store record), drags the light on a
sphere (or picks an HDR map and a rotation), sets the shadow strength and the sampler, and sees the relit photo
with the seconds it took and the model's reconstruction error (``difareli.app``).

    difareli-app [checkpoint=difareli_pp-synth64] [store=<store>] [port=8765]
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf

from difareli import errors
from difareli.cli.common import CONFIG_PATH


def build_service(cfg: DictConfig):
    """The app's :class:`~difareli.app.service.Service` from the config, with the default model loaded."""
    from difareli.app.service import Service

    if cfg.store is not None:
        errors.check_file(f"{cfg.store}/store.json", "store")
    svc = Service(checkpoint=str(cfg.checkpoint), store=None if cfg.store is None else str(cfg.store),
                  runtime=OmegaConf.to_container(cfg.runtime, resolve=True),
                  composite=OmegaConf.to_container(cfg.composite, resolve=True))
    svc.relighter(None)  # a bad checkpoint stops here, with the CLI's message
    return svc


def warm_up(svc) -> None:
    """Build the photo pipeline and run it once (mediapipe graphs, dlib), so the first upload is fast."""
    import numpy as np

    try:
        from difareli.relight.photo import pipeline_for

        rel = svc.relighter(None)
        size = int(rel.config.get("input_dims", {}).get("resolution", 64))
        pipe = pipeline_for(list(dict.fromkeys([*rel.needed_encodings(), "face_mask", "masks"])), size)
        from skimage import data

        pipe.process(np.ascontiguousarray(data.astronaut()))
    except ImportError as e:
        print(f"photo uploads need the estimators ({e}); DIFARELI_PREPROCESS=1 bash scripts/install.sh")


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="app")
@errors.cli_entry("app")
def main(cfg: DictConfig) -> None:
    from difareli.app.server import make_server

    errors.check_int(cfg.port, "port", 0)
    svc = build_service(cfg)
    if cfg.warm:
        warm_up(svc)
    server = make_server(svc, str(cfg.host), int(cfg.port))
    print(f"difareli-app: open http://{cfg.host}:{server.server_port}/ (Ctrl-C stops)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: nothing to resume, just stop
        print("difareli-app: stopped")
    finally:
        server.server_close()


if __name__ == "__main__":
    main()
