"""difareli-app: a local web page where a user drops a face photo (or picks a store record), drags the light on a
sphere (or picks an HDR map and a rotation), sets the shadow strength and the sampler, and sees the relit photo
with the seconds it took and the model's reconstruction error (``difareli.app``).

    difareli-app [checkpoint=difareli_pp_ss_est-synth64] [store=<store>] [port=8765] [checkpoints=[<file or folder>]]
                 [server.queue=8] [server.connections=64]

It binds its port first (a port in use is one line, before the model loads), serves 127.0.0.1 unless told
otherwise, and lets a request name only the shipped checkpoints and those given here. ``server`` bounds the crowd it
holds (:class:`difareli.app.server.Limits`): past them a request is answered 503 with Retry-After or waits.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf

from difareli import errors
from difareli.cli.common import CONFIG_PATH


def _list(value) -> list[str]:
    if value is None:
        return []
    return [str(v) for v in value] if OmegaConf.is_list(value) or isinstance(value, (list, tuple)) else [str(value)]


def build_service(cfg: DictConfig):
    """The app's :class:`~difareli.app.service.Service` from the config, with the default model loaded."""
    from difareli.app.service import Service

    if cfg.store is not None:
        errors.check_file(f"{cfg.store}/store.json", "store")
    cache = cfg.get("cache") or {}
    sizes = {f"max_{k}": errors.check_int(cache.get(k, d), f"cache.{k}", 1)
             for k, d in (("relighters", 3), ("sources", 8), ("inversions", 8))}
    svc = Service(checkpoint=str(cfg.checkpoint), store=None if cfg.store is None else str(cfg.store),
                  runtime=OmegaConf.to_container(cfg.runtime, resolve=True),
                  composite=OmegaConf.to_container(cfg.composite, resolve=True),
                  checkpoints=tuple(_list(cfg.get("checkpoints"))), **sizes)
    svc.relighter(None)  # a bad checkpoint stops here, with the CLI's message
    return svc


def warm_up(svc) -> None:
    """Build the photo pipeline and run it once (mediapipe graphs, dlib), so the first upload is fast."""
    import numpy as np

    try:
        from difareli.relight.photo import pipeline_for

        rel = svc.relighter(None)
        size = rel.photo_size()  # the training resolution (a checkpoint without one is refused, naming photo_size)
        pipe = pipeline_for(list(dict.fromkeys([*rel.needed_encodings(), "face_mask", "masks"])), size)
        from skimage import data

        pipe.process(np.ascontiguousarray(data.astronaut()))
    except ImportError as e:
        print(f"photo uploads need the estimators ({e}); DIFARELI_PREPROCESS=1 bash scripts/install.sh")


def limits(cfg: DictConfig):
    """The crowd the server holds (:class:`~difareli.app.server.Limits`) from ``server``, checked."""
    from difareli.app.server import Limits

    srv, d = cfg.get("server") or {}, Limits()
    queue = errors.check_int(srv.get("queue", d.queue), "server.queue", 1)
    connections = errors.check_int(srv.get("connections", d.connections), "server.connections", 1)
    if connections <= queue:
        raise errors.UserError(f"server.connections={connections} is not above server.queue={queue}: each queued "
                               f"request holds a connection, and the page needs one more; e.g. server.connections="
                               f"{8 * queue}")
    backlog = errors.check_int(srv.get("backlog", d.backlog), "server.backlog", 1, maximum=65535)
    read_timeout = errors.check_number(srv.get("read_timeout", d.read_timeout), "server.read_timeout",
                                       allow_none=False, limit=3600)
    if read_timeout <= 0:
        raise errors.UserError(f"server.read_timeout={read_timeout:g} is invalid: give the seconds a client has to "
                               "send its request, e.g. server.read_timeout=20")
    return Limits(queue, connections, backlog, read_timeout)


def bind(cfg: DictConfig):
    """The server bound to ``host:port`` without a service yet; a port in use (or a host not on this machine) or
    bad ``server`` limits are a UserError before anything slow happens."""
    from difareli.app.server import make_server

    port = errors.check_int(cfg.port, "port", 0)
    if port > 65535:
        raise errors.UserError(f"port={port} is invalid: must be 0..65535; e.g. port=8765")
    bounds = limits(cfg)
    try:
        return make_server(None, str(cfg.host), port, allowed_hosts=tuple(_list(cfg.get("allowed_hosts"))),
                           limits=bounds)
    except OSError as e:
        raise errors.UserError(f"port={port}: cannot listen on {cfg.host}:{port} ({e.strerror or e}); stop the "
                               "program using it or give another port, e.g. port=0 (any free port)") from None


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="app")
@errors.cli_entry("app")
def main(cfg: DictConfig) -> None:
    server = bind(cfg)
    try:
        svc = build_service(cfg)
        if cfg.warm:
            warm_up(svc)
        server.RequestHandlerClass.service = svc
        if str(cfg.host) not in ("127.0.0.1", "localhost", "::1"):
            print(f"difareli-app: warning: host={cfg.host} serves other machines too", flush=True)
        b = server.limits
        print(f"difareli-app: open http://{cfg.host}:{server.server_port}/ (Ctrl-C stops; it queues at most "
              f"{b.queue} relight requests, more are answered 503)", flush=True)
        server.serve_forever()
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: nothing to resume, just stop
        print("difareli-app: stopped")
    finally:
        server.server_close()


if __name__ == "__main__":
    main()
