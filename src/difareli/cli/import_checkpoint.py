"""difareli-import-checkpoint: the authors' DiFaReli checkpoint -> a difareli checkpoint for any CLI's checkpoint=.

    difareli-import-checkpoint <ImgCond_ema_0.9999_<step>.pt | its folder> config=<official YAML> out=<name>.ckpt
        [encoder=<ImgEncoder_ema_0.9999_<step>.pt>] [step=<n>] [ema=0.9999|model]
        [shape_parts=shape,exp,pose | store=<store from difareli.official.importers>] [verify=true|false]

The official code (github.com/diffusion-face-relighting/difareli_code) saves the UNet and its Modulator as two
plain state dicts; the Modulator file is found beside the UNet by name unless ``encoder=`` gives it. ``config=`` is
the YAML the checkpoint was trained with (e.g. ``config/difareli/difareli_128.yaml``). ``shape_parts`` (or
``store=``, read from its ``shape_layout``) is the order of the DECA parts in the ``shape`` encoding of the
stores the model will relight (``difareli.official.importers`` writes shape, exp, pose). ``verify`` (default on) reloads
the written file the normal way and checks that its eps equals the converted network's exactly.
Any CLI given an official file as ``checkpoint=`` stops with a message naming this command.
"""

from difareli.utils.processes import openmp_for_machine

openmp_for_machine()  # before torch loads: idle OpenMP threads sleep on a busy machine (docs/scaling_out.md)

import sys

from difareli.cli.argv import argv_or_help
from difareli.errors import UserError, check_int, cli_entry

KEYS = ("official", "config", "out", "encoder", "step", "ema", "shape_parts", "store", "verify")
USAGE = ("usage: difareli-import-checkpoint <ImgCond_ema_0.9999_<step>.pt | folder> config=<official YAML> "
         "out=<name>.ckpt [encoder=...] [step=N] [ema=0.9999|model] [shape_parts=shape,exp,pose | store=<store>] "
         "[verify=true|false]")


def parse(argv: list[str]) -> dict[str, str]:
    """``key=value`` tokens (and one bare path: ``official``) -> options; unknown keys are a UserError."""
    opts: dict[str, str] = {}
    for token in argv:
        key, sep, value = token.partition("=")
        if not sep:
            key, value = "official", token
        if key not in KEYS:
            raise UserError(f"unknown option {key!r}; known: {', '.join(KEYS)}\n{USAGE}")
        if key in opts:
            raise UserError(f"{key} given twice ({opts[key]!r}, {value!r})\n{USAGE}")
        opts[key] = value
    for key in ("official", "config", "out"):
        if not opts.get(key):
            raise UserError(f"{key} is missing\n{USAGE}")
    return opts


def _bool(value: str, key: str) -> bool:
    if value.lower() in ("true", "1", "yes"):
        return True
    if value.lower() in ("false", "0", "no"):
        return False
    raise UserError(f"{key}={value!r} is not true or false")


@cli_entry("import-checkpoint")
def main(argv: list[str] | None = None) -> int:
    argv = argv_or_help(argv, __doc__)
    if argv is None:
        return 0
    from difareli.official import weights as official
    opts = parse(argv)
    step = check_int(int(opts["step"]) if opts.get("step", "").isdigit() else opts.get("step"), "step", 0,
                     allow_none=True)
    if opts.get("shape_parts") and opts.get("store"):
        raise UserError("give shape_parts= or store=, not both")
    parts = (opts["shape_parts"].split(",") if opts.get("shape_parts")
             else official.shape_parts_of(opts["store"]) if opts.get("store") else None)
    summary = official.import_checkpoint(opts["official"], opts["config"], opts["out"], encoder=opts.get("encoder"),
                                         step=step, ema=opts.get("ema", "0.9999"), shape_parts=parts,
                                         verify=_bool(opts.get("verify", "true"), "verify"))
    dims = summary["input_dims"]
    for line in summary.get("warnings", []):
        print(f"difareli-import-checkpoint: {line}", file=sys.stderr)
    print(f"difareli-import-checkpoint: {summary['unet']} + {summary['modulator']} (step {summary['step']}) -> "
          f"{summary['out']}: {summary['parameters']:,} parameters")
    print(f"  spatial inputs {summary['spatial_inputs']} ({dims['spatial_channels']} channels), non-spatial "
          f"{summary['nonspatial_inputs']} ({dims['nonspatial_dim']} values; shape = {summary['shape_parts']}), "
          f"{dims['resolution']} px")
    print("  from config (the tensors cannot show these; check them against the run's YAML): "
          + ", ".join(summary.get("config_notes", [])))
    if "max_abs_diff" in summary:
        print(f"  reloaded with load_checkpoint: max |eps difference| {summary['max_abs_diff']:.1e}")
    print(f"  use it: difareli-relight checkpoint={summary['out']} store=<store from difareli.official.importers> ...")
    return 0


def entry() -> None:
    """Console-script entry point: exit with main's status."""
    sys.exit(main())


if __name__ == "__main__":
    entry()
