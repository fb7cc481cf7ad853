"""Make the pictures of docs/gallery.md: run each figure and lab scene at a moderate scale, render a strip.

    python docs/make_gallery.py                       # every figure scene (about 15 min on one core)
    python docs/make_gallery.py fig5_hyperelastic_boxes fig6_dough_star
    python docs/make_gallery.py --render-only         # re-render from the kept USD files

Each scene is run with ``warp-esph run NAME --scale S`` into ``--work`` (default
``/tmp/warp_esph_gallery``) and rendered with ``warp-esph render`` to
``docs/images/NAME.png``: a strip of four frames, quantised to 256 colours where that is
needed to keep the PNG under 150 kB.
"""

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
sys.path.insert(0, REPO)

#: scene, scale, frames of the strip, extra render options (as for ``warp-esph render``).
GALLERY = [
    ("fig1_non_newtonian", 0.5, "0,9,14,60", []),
    ("fig2_three_cylinders", 0.4, "0,5,8,50", []),
    ("fig3_pile", 0.8, "0,7,14,60", ["--fit", "each"]),
    ("fig4_bunny_on_sphere", 0.5, "0,5,10,50", []),
    ("fig5_hyperelastic_boxes", 1.0, "0,6,9,50", []),
    ("fig6_dough_star", 0.6, "0,5,20,75", []),
    ("fig7_plastic_grid", 0.4, "0,6,10,50", []),
    ("fig8_comparison", 0.8, "0,7,12,25", []),
    # The lab tests with tools (docs/tools.md), drawn at each frame's tool pose.
    ("lab_compression", 0.5, "0,20,40,60", ["--elevation", "6"]),
    ("lab_indentation", 0.5, "0,15,30,60", []),
    ("lab_three_point_bending", 0.5, "0,20,40,60", []),
    ("lab_cutting", 0.5, "0,10,20,30", []),
    ("lab_fig8_plates", 0.5, "0,7,9,25", []),
]
WIDTH, HEIGHT = 360, 270


def main(argv=None) -> int:
    from PIL import Image

    from warp_esph.cli import main as cli

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="*", help="scene names (default: all of GALLERY)")
    p.add_argument("--work", default="/tmp/warp_esph_gallery", help="folder for the USD files")
    p.add_argument("--render-only", action="store_true", help="do not run; render the USD files in --work")
    args = p.parse_args(argv)
    wanted = args.scenes or [g[0] for g in GALLERY]
    os.makedirs(args.work, exist_ok=True)
    out_dir = os.path.join(HERE, "images")
    os.makedirs(out_dir, exist_ok=True)
    for name, scale, frames, extra in GALLERY:
        if name not in wanted:
            continue
        usd = os.path.join(args.work, f"{name}.usdc")
        if not args.render_only:
            t0 = time.perf_counter()
            status = cli(["run", name, "--scale", str(scale), "-o", usd, "--no-progress"])
            print(f"{name}: run {time.perf_counter() - t0:.0f} s (status {status})", flush=True)
            if status != 0:
                return status
        png = os.path.join(out_dir, f"{name}.png")
        status = cli(["render", usd, "-o", png, "--frames", frames, "--width", str(WIDTH), "--height", str(HEIGHT),
                      "--columns", "4", *extra])
        if status != 0:
            return status
        if os.path.getsize(png) > 140 * 1024:
            img = Image.open(png).convert("RGB")
            img.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(png, optimize=True)
        print(f"{name}: {png} {os.path.getsize(png) / 1024:.0f} kB", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
