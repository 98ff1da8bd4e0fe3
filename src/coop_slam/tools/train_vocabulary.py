"""Train the team's shared ORB bag-of-words vocabulary from images, TUM or synthetic data.

Every input option may be repeated; all frames used train one vocabulary.
"""

import argparse
import sys
import time

from ..bow.training import ConsoleProgress, ExtractionConfig, image_files, train_from_sequences
from ..bow.vocabulary import DEFAULT_K, DEFAULT_LEVELS, VocabularyConfig
from ..datasets import read_tum
from ..default_vocabulary import synthetic_sequences
from ..errors import CoopSlamError


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="scripts/train_vocabulary", description=__doc__)
    parser.add_argument(
        "--images", action="append", default=[], metavar="DIR", help="image folder (recursive)"
    )
    parser.add_argument(
        "--tum", action="append", default=[], metavar="DIR", help="TUM RGB-D sequence folder"
    )
    parser.add_argument(
        "--synthetic", action="append", default=[], metavar="DIR", help="synthetic world folder"
    )
    parser.add_argument("--every", type=int, default=5, metavar="N", help="use every N-th frame")
    parser.add_argument("--features", type=int, default=1000, help="ORB features per image")
    parser.add_argument("-k", type=int, default=DEFAULT_K, help="branching factor")
    parser.add_argument("-L", type=int, default=DEFAULT_LEVELS, help="depth (levels)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out",
        required=True,
        metavar="FILE",
        help="output vocabulary: .npz (own format) or .txt (DBoW2/ORBvoc text)",
    )
    args = parser.parse_args(argv)
    if not (args.images or args.tum or args.synthetic):
        parser.error("give training data with --images, --tum and/or --synthetic")
    try:
        sequences = [read_tum(folder) for folder in args.tum]
        for folder in args.synthetic:
            sequences.extend(synthetic_sequences(folder))
        paths = [p for folder in args.images for p in image_files(folder)]
        start = time.perf_counter()
        vocab = train_from_sequences(
            sequences,
            paths,
            extraction=ExtractionConfig(features=args.features, every=args.every),
            vocabulary=VocabularyConfig(k=args.k, levels=args.L, seed=args.seed),
            out=args.out,
            progress=ConsoleProgress(sys.stderr),
        )
    except CoopSlamError as exc:
        print(f"train_vocabulary: error: {exc}", file=sys.stderr)
        return 1
    print(f"{vocab} trained in {time.perf_counter() - start:.1f} s, saved to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
