"""Meshes out and in: ``voxe export-mesh`` (marching cubes, PLY / GLB / OBJ) and ``voxe mesh-to-grid`` (an OBJ or PLY as G_i)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from voxe_core.cli.common import (
    EXIT_INTERRUPTED, add_device_argument, add_grid_output_arguments, check_device, finite_float, int_list,
    int_list_at_most, positive_int, positive_int_at_most, run_stage, said_by_option, say_grid_notes, seed, tensor_file,
    writable_file,
)
from voxe_core.cli.reconstruct import RESOLUTION_SETTINGS, recipe_params
from voxe_core.constants import (
    MAX_GRID_RESOLUTION, MAX_MESH_RESOLUTION, MAX_RAYS_PER_STEP, MESH_SUFFIXES, MIN_GRID_RESOLUTION,
)
from voxe_core.presets import (
    DOWNSAMPLE, MESH_VIEW_SIZE, MESH_VIEWS, RECONSTRUCTION_PRESET, RECONSTRUCTION_PRESETS, SEED, ExportConfig,
    reconstruct_config,
)


def add_parsers(commands, common) -> None:
    mesh = commands.add_parser(
        "export-mesh", parents=[common], help="marching-cubes mesh with vertex colours (.ply, .glb or .obj + .mtl)"
    )
    mesh.add_argument("grid", type=Path, metavar="GRID")
    mesh.add_argument("--out", type=Path, required=True, help="mesh file, .ply, .glb or .obj")
    mesh.add_argument("--level", type=finite_float, default=None, help="surface density (default ln 2 / voxel size)")
    mesh.add_argument("--resolution", type=positive_int_at_most(MAX_MESH_RESOLUTION),
                      default=ExportConfig.mesh_resolution,
                      help=f"resample to N points per axis (at most {MAX_MESH_RESOLUTION})")
    add_device_argument(mesh)
    mesh.set_defaults(run=cmd_export_mesh)

    mg = commands.add_parser("mesh-to-grid", parents=[common],
                             help="an initial grid from an OBJ or PLY mesh (+ texture)")
    mg.add_argument("mesh", type=Path, metavar="MESH", help=".obj or .ply")
    mg.add_argument("--texture", type=Path, default=None,
                    help="the mesh's texture image, at its UVs (in place of the one it names)")
    mg.add_argument("--up", choices=("x", "y", "z"), default="y", help="the mesh file's up axis (OBJ: y)")
    mg.add_argument("--shading", choices=("auto", "baked", "none"), default="auto",
                    help="bake a fixed light + ambient occlusion into the colour (auto: for meshes without colour)")
    mg.add_argument("--route", choices=("voxelize", "render"), default="voxelize",
                    help="voxelize: write the mesh into the grid; render: reconstruct from rendered views")
    mg.add_argument("--out", type=tensor_file, required=True, help="grid file to write (.safetensors)")
    add_grid_output_arguments(mg)
    mg.add_argument("--views", type=positive_int, default=None,
                    help=f"render route: upper-hemisphere views (default {MESH_VIEWS})")
    mg.add_argument("--size", type=positive_int, default=None,
                    help=f"render route: view size in pixels (default {MESH_VIEW_SIZE // DOWNSAMPLE}: what the "
                         f"service's fit sees, its {MESH_VIEW_SIZE} px views loaded at 1/{DOWNSAMPLE})")
    mg.add_argument("--preset", choices=RECONSTRUCTION_PRESETS, default=RECONSTRUCTION_PRESET,
                    help="render route: reconstruction preset")
    mg.add_argument("--resolution", type=int_list_at_most(MAX_GRID_RESOLUTION, MIN_GRID_RESOLUTION), default=None,
                    metavar="N[,N...]", help="grid resolution (voxelize: default the preset's final one, as the "
                    f"service's; render: as voxe reconstruct; the final at least {MIN_GRID_RESOLUTION}, at most "
                    f"{MAX_GRID_RESOLUTION})")
    mg.add_argument("--iterations", type=int_list, default=None, metavar="N[,N...]", help="render route: as voxe reconstruct")
    mg.add_argument("--rays", type=positive_int_at_most(MAX_RAYS_PER_STEP), default=None,
                    help=f"render route: rays per step (at most {MAX_RAYS_PER_STEP})")
    mg.add_argument("--seed", type=seed, default=SEED)
    add_device_argument(mg)  # the render route's reconstruction (the voxeliser is CPU code)
    mg.set_defaults(run=cmd_mesh_to_grid)


def cmd_export_mesh(args) -> int:
    if args.out.suffix.lower() not in MESH_SUFFIXES:  # before torch: seconds to be told
        raise ValueError(f"--out: unsupported mesh suffix {args.out.suffix!r} for {args.out}; use one of "
                         f"{', '.join(MESH_SUFFIXES)}")
    from voxe_core.backbones import load_grid
    from voxe_core.export import extract_mesh, save_mesh

    device = check_device(args)
    writable_file(args.out)
    if args.out.suffix.lower() == ".obj":  # and the material library beside it, before the mesh is made
        writable_file(Path(os.path.realpath(args.out)).with_suffix(".mtl"))  # (save_obj's: a symlink's target's)
    grid = load_grid(args.grid).to(device)  # the density lattice is sampled there; marching cubes runs on the CPU
    say_grid_notes(args, args.grid)  # (a mesh file carries no note: said on stderr alone)
    with said_by_option({"mesh resolution": "--resolution"}):
        mesh = extract_mesh(grid, level=args.level, resolution=args.resolution)
    save_mesh(mesh, args.out)
    print(f"wrote {args.out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces")
    return 0


def cmd_mesh_to_grid(args) -> int:
    from voxe_core.mesh_input import (VoxelizeConfig, hemisphere_cameras, load_mesh, render_mesh_views, shade_mesh,
                                      voxelize)
    from voxe_core.reconstruct import reconstruct

    render_only = [flag for flag, value in (("--views", args.views), ("--size", args.size),
                                            ("--iterations", args.iterations), ("--rays", args.rays)) if value is not None]
    if args.route == "voxelize" and render_only:  # (they had been taken and ignored)
        raise ValueError(f"{', '.join(render_only)} set the render route's views and fit; --route voxelize writes "
                         "the mesh into the grid (--resolution sets its size)")
    device = check_device(args)
    writable_file(args.out)
    mesh = shade_mesh(load_mesh(args.mesh, args.texture, args.up), args.shading)
    if args.route == "voxelize":  # as the service's mesh scenes: the preset's final resolution and box
        if args.resolution is not None and len(args.resolution) != 1:
            raise ValueError(f"--resolution takes one value for the voxelize route, got {len(args.resolution)}")
        fit = reconstruct_config({**recipe_params(args), "resolution": None, "iterations": None})  # (render's)
        resolution = fit.resolutions[-1] if args.resolution is None else args.resolution[0]
        with said_by_option(RESOLUTION_SETTINGS):
            grid = voxelize(mesh, VoxelizeConfig(resolution=resolution, bbox_min=fit.bbox_min, bbox_max=fit.bbox_max,
                                                 seed=args.seed))
    else:
        with said_by_option(RESOLUTION_SETTINGS):
            config = reconstruct_config(recipe_params(args))
        cameras = hemisphere_cameras(MESH_VIEWS if args.views is None else args.views,
                                     MESH_VIEW_SIZE // DOWNSAMPLE if args.size is None else args.size, args.seed)
        images, _ = render_mesh_views(mesh, cameras)
        grid = run_stage(lambda callbacks: reconstruct(images, cameras, config, callbacks, device=device),
                         "reconstruct", "it", config.total_iterations, args.quiet)
        if grid is None:
            print(f"voxe: reconstruction cancelled, nothing written to {args.out}", file=sys.stderr)
            return EXIT_INTERRUPTED
    grid.save(args.out, dense=args.dense)
    print(f"wrote {args.out}: {'x'.join(map(str, grid.resolution))} grid from {args.mesh.name} ({args.route})")
    return 0
