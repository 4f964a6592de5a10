"""Pack exported ``mjwarp`` scenes for the GPU machine: one ``tar.xz`` a scene, textures reduced.

Each (task, protocol) is exported first when it is not cached (:func:`vecsim.engine.mjwarp.scene.export_scene`,
the CPU stack); a scene the ``mjwarp`` engine would refuse is left out; the others are packed
as ``<out>/<folder>.tar.xz``, to be unpacked into the device's ``$VECSIM_MJWARP_SCENES``
(``tar xJf X.tar.xz -C /tmp/scenes``). Textures wider or higher than ``--max-texture`` are
halved as the device bundle halves the CPU engine's (``scripts/build_device_bundle.py``), so
both engines draw the same texels. ``<out>/index.json`` lists every archive with its bytes, and
every scene left out with the reason. A device call carries at most 64 MiB in all:
``--together NAME.tar.xz`` packs every scene into one archive instead, each mesh and texture
they share held once (hard links).

    python scripts/pack_mjwarp_scenes.py libero_10/0 libero_10/1 --libero '{}' '{"settle_steps": 15}' \\
        --together scenes.tar.xz
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import logging
import sys
import tarfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from build_device_bundle import reduced_texture  # noqa: E402

from vecsim.config import LiberoProtocol  # noqa: E402
from vecsim.engine.mjwarp.scene import export_scene, load_scene, refusal  # noqa: E402

log = logging.getLogger("pack_mjwarp_scenes")


class Packer:
    """Scene folders into ``tar.xz`` archives, each PNG texture reduced once per content."""

    def __init__(self, max_texture: int) -> None:
        self.max_texture = max_texture
        self._reduced: dict[str, bytes | None] = {}

    def files(self, folder: Path) -> list[tuple[str, bytes | None, Path, str]]:
        """``(name in the archive, reduced bytes or None, path, content digest)`` of every file."""
        out = []
        for path in sorted(folder.rglob("*")):
            if not path.is_file():
                continue
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
            if path.suffix.lower() == ".png" and digest not in self._reduced:
                self._reduced[digest] = reduced_texture(path, self.max_texture)
            out.append((f"{folder.name}/{path.relative_to(folder)}", self._reduced.get(digest), path, digest))
        return out

    def pack(self, folders: list[Path], archive: Path) -> Path:
        """Write ``archive`` holding ``folders`` under their names; a file whose content another
        already holds is stored as a hard link to it (scenes share most meshes and textures)."""
        first: dict[str, str] = {}
        with tarfile.open(archive, "w:xz") as tar:
            for folder in folders:
                for name, reduced, path, digest in self.files(folder):
                    if digest in first:
                        info = tarfile.TarInfo(name)
                        info.type, info.linkname, info.mode = tarfile.LNKTYPE, first[digest], 0o644
                        tar.addfile(info)
                        continue
                    first[digest] = name
                    if reduced is None:
                        tar.add(path, arcname=name)
                        continue
                    info = tarfile.TarInfo(name)
                    info.size, info.mode, info.mtime = len(reduced), 0o644, int(path.stat().st_mtime)
                    tar.addfile(info, io.BytesIO(reduced))
        return archive


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tasks", nargs="+", help="LIBERO task ids (libero_10/0 ...)")
    parser.add_argument(
        "--libero",
        nargs="+",
        type=LiberoProtocol.model_validate_json,
        default=[LiberoProtocol()],
        help="one or more job libero blocks as JSON (default: LIBERO's published protocol)",
    )
    parser.add_argument("--root", type=Path, default=None, help="the scenes' cache (default: the engine's)")
    parser.add_argument("--out", type=Path, default=Path(".whl/scenes"), help="where the archives go")
    parser.add_argument("--together", help="one archive of that name holding every scene (shared files once) instead")
    parser.add_argument("--max-texture", type=int, default=512, help="largest texture side packed, in pixels")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    index_path = args.out / "index.json"
    index = json.loads(index_path.read_text()) if index_path.is_file() else {}
    packer, folders = Packer(args.max_texture), []
    for protocol in args.libero:
        for task_id in args.tasks:
            key = f"{task_id} {protocol.model_dump_json()}"
            try:
                folder = export_scene(task_id, protocol, root=args.root)
            except ValueError as exc:
                log.error("%s: not exported: %s", task_id, exc)
                index[key] = {"task": task_id, "error": str(exc)}
                continue
            refused = refusal(load_scene(folder).manifest)
            if refused:
                # The engine would refuse it: not worth carrying.
                log.info("%s: not packed: %s", folder.name, refused)
                index[key] = {"task": task_id, "libero": protocol.model_dump(), "refused": refused}
                continue
            folders.append(folder)
            if args.together:
                continue
            archive = packer.pack([folder], args.out / f"{folder.name}.tar.xz")
            index[archive.name] = {"task": task_id, "libero": protocol.model_dump(), "bytes": archive.stat().st_size}
            log.info("%s %.1f MB", archive.name, archive.stat().st_size / 1e6)
            index_path.write_text(json.dumps(index, indent=1, sort_keys=True) + "\n")
    if args.together and folders:
        archive = packer.pack(folders, args.out / args.together)
        index[archive.name] = {"scenes": [f.name for f in folders], "bytes": archive.stat().st_size}
        log.info("%s %.1f MB: %d scenes", archive.name, archive.stat().st_size / 1e6, len(folders))
    index_path.write_text(json.dumps(index, indent=1, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
