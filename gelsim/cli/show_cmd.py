"""``gelsim show``: pictures of one sequence of a dataset: frames, marker field, labels over time (gelsim.show)."""
from __future__ import annotations


def register(sub) -> None:
    from ..show import DEFAULT_FRAMES, VIDEO_FPS
    from . import HelpFormatter

    p = sub.add_parser(
        "show", formatter_class=HelpFormatter,
        help="pictures of one sequence: its frames, its marker field, its labels over time",
        description=(
            "Write pictures of one sequence of a dataset made by `gelsim generate` into --out:\n"
            "  frames.png   evenly spaced frames as the dataset holds them and, below each, the frame minus\n"
            "               the flat gel of the dataset's sensor, contrast stretched (what the contact changed)\n"
            "  markers.png  the markers' displacement from rest as arrows (magnified; the caption says how\n"
            "               much) at the first contact frame and the frames of peak force, shear and twist\n"
            "  labels.png   the labels over time: normal and tangential force, shear, twist, contact area,\n"
            "               the contact onset and the slipping frames; the nuisance applied to each frame\n"
            "               when the dataset has a per-frame nuisance record\n"
            f"  video.mp4    with --video: the sequence at {VIDEO_FPS:g} frames per second (a third of the camera's\n"
            "               rate), each frame beside its difference with the marker arrows\n"
            "Sequence ids are in DIR/manifest.json (sequences[].id), e.g. f001-s0000."),
    )
    p.add_argument("dir", metavar="DIR", help="dataset directory (the --out of gelsim generate)")
    p.add_argument("sequence", metavar="SEQUENCE", nargs="?", default=None,
                   help="sequence id, e.g. f001-s0000 (default: the first sequence with a contact)")
    p.add_argument("--out", metavar="FOLDER", default=None,
                   help="folder for the pictures (default: DIR/previews/SEQUENCE)")
    p.add_argument("--frames", type=int, metavar="N", default=DEFAULT_FRAMES,
                   help="frames in frames.png's strip, the first and the last included (count)")
    p.add_argument("--video", action="store_true", help="also write video.mp4 (H.264)")
    p.add_argument("--json", action="store_true", help="print {sequence, out, files, ...} as one JSON document")
    p.set_defaults(handler=run_show)


def run_show(args) -> int:
    from ..atomic import out_folder
    from ..show import load_look, show
    from . import print_result

    if args.frames < 1:
        from ..errors import GelsimError

        raise GelsimError(f"--frames {args.frames} is invalid; give how many frames the strip shows, 1 or more")
    look = load_look(args.dir, args.sequence)     # bad input is found before any folder is made
    out = args.out if args.out is not None else f"{args.dir}/previews/{look.sequence['id']}"
    with out_folder(out):
        res = show(args.dir, out=out, frames=args.frames, video=args.video, look=look)
    return print_result(args.json, res, *res["files"])
