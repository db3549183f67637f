"""difareli-export: a checkpoint -> a weights folder that loads with no pickle.

    difareli-export <checkpoint: a .ckpt file or a shipped name> <folder> [verify=true|false]

Writes ``<folder>/model.safetensors`` (the EMA weights the relight uses), ``config.json`` (the module class, the
plain hyperparameters with the normalisation statistics, the step) and ``README.md`` (the model card: the shipped
one for a shipped checkpoint). Every ``checkpoint=`` then takes ``<folder>`` (``load_checkpoint`` reads it with
``safetensors`` and ``json`` only). ``verify`` (default on) reloads both and checks that every tensor is equal.
"""

from __future__ import annotations

import sys

from difareli.checkpoints import loading
from difareli.cli.argv import argv_or_help
from difareli.errors import UserError, cli_entry

USAGE = "usage: difareli-export <checkpoint: .ckpt file or shipped name> <folder> [verify=true|false]"


def parse(argv: list[str]) -> tuple[str, str, bool]:
    """(checkpoint, folder, verify) from the command line; anything else is a UserError with the usage."""
    paths = [a for a in argv if "=" not in a]
    opts = dict(a.split("=", 1) for a in argv if "=" in a)
    if len(paths) != 2:
        raise UserError(f"give a checkpoint and a folder (got {len(paths)} path(s): {paths})\n{USAGE}")
    unknown = set(opts) - {"verify"}
    if unknown:
        raise UserError(f"unknown option(s) {sorted(unknown)}; known: verify\n{USAGE}")
    verify = opts.get("verify", "true").lower()
    if verify not in ("true", "false", "1", "0"):
        raise UserError(f"verify={opts['verify']!r} is not true or false\n{USAGE}")
    return paths[0], paths[1], verify in ("true", "1")


def verify_folder(checkpoint: str, folder: str) -> int:
    """Reload the .ckpt and the folder; the number of tensors, all equal (a ValueError names the first that is
    not)."""
    import torch

    from difareli.checkpoints.export import read_folder

    a, b = loading.read_checkpoint(loading.resolve(checkpoint)), read_folder(folder)
    if set(a["state_dict"]) != set(b["state_dict"]):
        raise UserError(f"{folder}: its tensors differ in names from {checkpoint}'s")
    for k, v in a["state_dict"].items():
        w = b["state_dict"][k]
        if v.dtype != w.dtype or not torch.equal(v, w):
            raise UserError(f"{folder}: tensor {k} differs from {checkpoint}'s")
    if a["hyper_parameters"] != b["hyper_parameters"]:
        raise UserError(f"{folder}: config.json's hyperparameters differ from {checkpoint}'s")
    return len(a["state_dict"])


@cli_entry("export")
def main(argv: list[str] | None = None) -> int:
    argv = argv_or_help(argv, __doc__)
    if argv is None:
        return 0
    from difareli.checkpoints.export import export_folder

    checkpoint, folder, verify = parse(argv)
    try:
        out = export_folder(checkpoint, folder)
        n = verify_folder(checkpoint, str(out)) if verify else None
    except (FileNotFoundError, ValueError) as e:
        raise UserError(str(e)) from None
    print(f"difareli-export: {checkpoint} -> {out} (model.safetensors, config.json, README.md)"
          + (f"; verified: {n} tensors equal" if n is not None else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
