"""Grid files: ``voxe convert-grid`` rewrites a grid sparse (the default of every command) or dense (``--dense``)."""

from __future__ import annotations

from pathlib import Path

from voxe_core.cli.common import non_negative_int, say_grid_notes, tensor_file, writable_file


def add_parsers(commands, common) -> None:
    convert = commands.add_parser("convert-grid", parents=[common],
                                  help="rewrite a grid file sparse (occupied cells + margin) or --dense")
    convert.add_argument("grid", type=Path, metavar="GRID", help="a grid file of either layout (or format version 1)")
    convert.add_argument("--out", type=tensor_file, required=True, help="grid file to write (.safetensors)")
    convert.add_argument("--dense", action="store_true", help="every vertex, as tools that want an (X, Y, Z, 4) array")
    convert.add_argument("--margin", type=non_negative_int, default=None,
                         help="sparse: cells kept around the occupied ones (default: the library's)")
    convert.set_defaults(run=cmd_convert_grid)


def cmd_convert_grid(args) -> int:
    from voxe_core.backbones import load_grid
    from voxe_core.gridfile import DEFAULT_MARGIN
    from voxe_core.tensorio import load_tensors

    if args.dense and args.margin is not None:
        raise ValueError("--margin sets the sparse layout's kept cells; --dense writes every vertex")
    grid = load_grid(args.grid)
    notes = say_grid_notes(args, args.grid)  # (a smoke-test edit's: the rewritten grid keeps it)
    before = args.grid.stat().st_size  # before the save: --out may be GRID itself
    writable_file(args.out)
    grid.save(args.out, dense=args.dense, margin=DEFAULT_MARGIN if args.margin is None else args.margin, notes=notes)
    _, meta = load_tensors(args.out, kind="voxel_grid", max_version=2)
    after = args.out.stat().st_size
    print(f"wrote {args.out}: {meta['layout']} {'x'.join(map(str, grid.resolution))} grid, "
          f"{after / 1e6:.2f} MB ({after / before:.2f}x of {args.grid.name})")
    return 0
