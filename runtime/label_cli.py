"""`vs2t-edge label CONFIG ITEM_ID FABRIC [--off-scene]`: the operator says what a piece in the reject bin was.
`vs2t-edge label CONFIG ITEM_ID --retract`: withdraws a piece's label (a wrong one); labelling a piece
again replaces its label instead of adding a second.
`vs2t-edge label CONFIG --last FABRIC`: labels the piece the cell decided last (a teach piece), and
refuses once the cell has begun another piece since (the piece decided last may then be a later
one than the operator saw: name it by ITEM_ID).
`vs2t-edge label CONFIG --list [N]`: the last N pieces sent to the reject bin, and what became of
their labels (none yet, waiting for the service, applied, or why not).

The label is appended, durably, to the file the cell config names (``evidence.operator_labels``);
the running service reads it before its next piece and re-estimates that untouched fabric's mean
from the piece's presses (runtime/labels.py), journaling whether it applied it and why not.
Checked here first: the config turns the mode on, FABRIC is a fabric of its scene (or, with
``--off-scene``, is not: a stranger the cell then learns to refuse), and the config's journal has
a decided piece ITEM_ID (a typo would otherwise only show as a refusal in the journal); what the
cell decided for it is printed with the label. A journal this command cannot read is said and the
label written anyway: the service journals a label it cannot use. ``--recording OUT`` labels a
piece of a `vs2t-edge record` session instead: checked against that recording's journal, written
to the same labels file (recorded pieces' ids, ``rec<time>-NNNNNN``, are never a live piece's).
"""

from __future__ import annotations

import sys
from collections import deque
from dataclasses import replace

from vs2t_edge.runtime.bundle import SEAL_KEY, BundleError, read_manifest
from vs2t_edge.runtime.config import load_config_or_say
from vs2t_edge.runtime.evidence import UNKNOWN
from vs2t_edge.runtime.labels import (alike_fabric, append_label, judged_anew, piece_digest, pre_sort_piece,
                                      read_labels, scene_fabric, typed_name)
from vs2t_edge.runtime.journal import iter_records


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("config", help="the cell config the service runs (evidence.operator_labels names the file)")
    parser.add_argument("item_id", nargs="?", help="the piece's item id, as the journal (and `--list`) show it")
    parser.add_argument("fabric", nargs="?", help="what the piece was: a fabric of the config's scene, or with "
                                                  "--off-scene any name for a fabric the job does not list")
    parser.add_argument("--list", nargs="?", type=int, const=20, default=None, metavar="N",
                        help="list the last N pieces (default 20) the journal sent to the reject bin, with their "
                             "labels, instead of labelling one")
    parser.add_argument("--retract", action="store_true",
                        help="withdraw ITEM_ID's label (a wrong one): the cell forgets what it learned from the "
                             "piece; to correct a label, label the piece again instead")
    parser.add_argument("--last", metavar="FABRIC", default=None,
                        help="label the piece the cell decided last as FABRIC, instead of ITEM_ID FABRIC (a teach "
                             "piece just pressed, whatever bin it went to); refused once the cell has begun another piece")
    parser.add_argument("--recording", metavar="OUT", default=None,
                        help="the piece is one of the `vs2t-edge record --out OUT` session's (checked against that "
                             "recording's journal instead of the service's)")
    parser.add_argument("--off-scene", action="store_true",
                        help="the piece is none of the job's fabrics: the cell learns it as a stranger, and pieces "
                             "like it go to the reject bin")


def run(args) -> int:
    if (cfg := load_config_or_say(args.config)) is None:
        return 2
    if cfg.operator_labels is None:
        print(f"label: {cfg.path} does not turn operator labels on; set evidence.operator_labels to a file "
              "(docs/operator_labels.md)", file=sys.stderr)
        return 2
    if getattr(args, "recording", None):
        from vs2t_edge.runtime.recording import recording_journal  # the daemon's imports: only when asked

        cfg = replace(cfg, journal=recording_journal(args.recording))
    if args.list is not None:
        if args.list < 1:
            print(f"label: --list {args.list}: give how many pieces to list (1 or more)", file=sys.stderr)
            return 2
        try:
            listed = rejected_pieces(cfg, args.list)
        except (OSError, ValueError) as exc:  # ValueError: InputRefused (a FIFO or a huge labels file)
            print(f"label: {exc}", file=sys.stderr)
            return 2
        # printed outside the try: a reader that closed the pipe (`--list | head`) is no journal error
        # (vs2t_edge/cli.py ends quietly on it)
        print("\n".join(listed))
        return 0
    if args.last is not None:
        if args.item_id is not None or args.retract:
            print("label: --last FABRIC takes no ITEM_ID (the piece is the one the journal decided last)",
                  file=sys.stderr)
            return 2
        args.fabric = args.last
    if args.item_id is not None:
        args.item_id = typed_name(args.item_id)
    if args.fabric is not None:  # as the scene spells it when it is one of its fabrics (the service compares exactly)
        args.fabric = scene_fabric(args.fabric, cfg.scene_classes) or typed_name(args.fabric)
    if args.retract:
        if args.item_id is None or args.fabric is not None or args.off_scene:
            print("label: --retract takes ITEM_ID alone (to correct a label, label the piece again)", file=sys.stderr)
            return 2
        if (found := _decided(cfg, args.item_id)) is None:
            return 2
        _, decided, piece = found
        try:
            append_label(cfg.operator_labels, args.item_id, None, piece=piece)
        except OSError as exc:
            print(f"label: cannot write {cfg.operator_labels}: {exc.strerror or exc}", file=sys.stderr)
            return 2
        print(f"{args.item_id}: label withdrawn in {cfg.operator_labels} (the service forgets the piece before its "
              f"next one){decided}")
        return 0
    if (args.item_id is None and args.last is None) or args.fabric is None:
        print("label: give ITEM_ID and FABRIC (or --list to see the pieces in the reject bin)", file=sys.stderr)
        return 2
    in_scene = args.fabric in cfg.scene_classes
    if not in_scene and (alike := alike_fabric(args.fabric, cfg.scene_classes)) is not None:
        # 'WOOL' for wool: as a stranger, wool's own presses would teach the cell to reject wool
        print(f"label: {args.fabric!r} is not a fabric of the scene in {cfg.path}, but {alike!r} is (names are "
              f"exact): label it {alike}", file=sys.stderr)
        return 2
    if in_scene == args.off_scene:
        print(f"label: {args.fabric!r} is {'a' if in_scene else 'not a'} fabric of the scene in {cfg.path} "
              f"({', '.join(cfg.scene_classes)})"
              + ("; drop --off-scene" if in_scene else "; a piece the job does not list takes --off-scene"),
              file=sys.stderr)
        return 2
    if (found := _decided(cfg, args.item_id)) is None:
        return 2
    args.item_id, decided, piece = found
    try:
        append_label(cfg.operator_labels, args.item_id, args.fabric, off_scene=args.off_scene, piece=piece)
    except OSError as exc:
        print(f"label: cannot write {cfg.operator_labels}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    kind = next((f.kind for f in cfg.fabrics if f.name == args.fabric), "off-scene")
    note = {"untouched": "", "off-scene": " (off-scene: pieces like it will go to the reject bin)",
            "touched": f" ({args.fabric} is touched: recorded, its mean stays the training one)"}[kind]
    print(f"{args.item_id} labelled {args.fabric} in {cfg.operator_labels}{note}{decided}")
    return 0


def _decided(cfg, item_id: str | None) -> tuple[str, str, str | None] | None:
    """(the piece's id, '; the cell had decided ...', its ``piece_digest``) for a decided piece
    ``item_id`` of the config's journal, or the last decided one for ``item_id`` None; ('', None when
    the journal cannot be read: said on stderr); None (refused, said) when the journal has no such
    piece, or the piece was decided under another bundle than the config's (the service would not
    use its label). The digest binds the label to this piece's presses (runtime/labels.py)."""
    last, found, begun = None, None, None
    # the bundle (its start record's seal) the session that decided each piece ran
    session_seal = last_seal = found_seal = None
    try:
        for rec in iter_records(cfg.journal):
            if rec.get("type") == "start":
                session_seal = rec.get(SEAL_KEY)
            elif rec.get("type") == "pre_sort" and rec.get("item_id") is not None:
                last, begun, last_seal = rec, None, session_seal
                if rec.get("item_id") == item_id:
                    found, found_seal = rec, session_seal
            elif rec.get("type") == "item" and rec.get("item_id") is not None:
                begun = rec  # a piece the cell began after the last decided one
    except OSError as exc:
        if item_id is None:
            print(f"label: cannot read the journal {cfg.journal} to find the last piece ({exc.strerror or exc})",
                  file=sys.stderr)
            return None
        print(f"label: cannot read the journal {cfg.journal} to check {item_id} ({exc.strerror or exc}); "
              "writing the label anyway - the service journals whether it could use it", file=sys.stderr)
        return item_id, "", None
    if item_id is None and last is not None and begun is not None and begun.get("item_id") != last.get("item_id"):
        # --last names the piece the operator just saw decided; once the line has begun another, the
        # last decided piece may already be a later one than that (a teach piece's label would then
        # teach its fabric another piece's presses, and every piece like that one would follow it)
        print(f"label: --last is ambiguous: the cell has begun piece {begun['item_id']} since it decided "
              f"{last['item_id']} (the cell had decided " + ("the reject bin" if last.get("label") == UNKNOWN
                                                               else last.get("label", "?"))
              + f"); name the piece: `vs2t-edge label {cfg.path} ITEM_ID FABRIC` (`--list` shows the pieces in "
              "the reject bin)", file=sys.stderr)
        return None
    found, found_seal = (last, last_seal) if item_id is None else (found, found_seal)
    if found is None:
        print(f"label: {cfg.journal} has no decided piece" + (f" {item_id!r}" if item_id is not None else "")
              + (f" (the last decided is {last['item_id']})" if last else " (no piece decided yet)")
              + f"; `vs2t-edge label {cfg.path} --list` shows the pieces in the reject bin"
              + ("; a recorded piece takes --recording OUT" if str(item_id).startswith("rec") else ""), file=sys.stderr)
        return None
    if (other := _another_bundle(cfg, found_seal)):
        print(f"label: piece {found['item_id']} was decided under another bundle than {cfg.bundle} ({other}); its "
              "presses are in that model's space, so the service would not use the label - label pieces decided "
              "under the bundle it runs", file=sys.stderr)
        return None
    label = found.get("label", "?")
    piece = piece_digest(*kept) if (kept := pre_sort_piece(found)) else None
    return str(found["item_id"]), ("; the cell had decided " + ("the reject bin" if label == UNKNOWN else label)
                                   + f" after {found.get('presses', '?')} press(es)"), piece


def _another_bundle(cfg, seal: str | None) -> str:
    """'' unless ``seal`` (a journal session's bundle) and the config's bundle are known and differ."""
    try:
        current = read_manifest(cfg.bundle).get(SEAL_KEY)
    except BundleError:
        return ""  # the service refuses an unreadable bundle itself; nothing to compare here
    if not (isinstance(seal, str) and isinstance(current, str)) or seal == current:
        return ""
    return f"seal {seal[:12]}, the config's bundle {current[:12]}"


def rejected_pieces(cfg, n: int) -> list[str]:
    """Lines for ``--list``: the last ``n`` pieces the journal sent to the reject bin, oldest first,
    each with its decision and its label's fate (the journal's label records, else the labels file)."""
    from vs2t_edge.runtime.sorting import reject_reason

    last: deque = deque(maxlen=n)
    fate: dict[str, str] = {}
    # the decision's reason (its pre_sort's stopped_by) of the pieces not yet final: a few at most, so a
    # long journal is read in bounded memory; kept with the piece's final record
    stopped_by: dict[str, str] = {}
    for rec in iter_records(cfg.journal):
        kind = rec.get("type")
        if kind == "pre_sort" and rec.get("item_id") is not None:
            stopped_by[str(rec["item_id"])] = str(rec.get("stopped_by") or "")
        if kind == "final":
            why = stopped_by.pop(str(rec.get("item_id")), "")
            if rec.get("bin") == cfg.reject_bin:
                last.append((rec, why))
        elif kind == "label" and rec.get("item_id") is not None and judged_anew(rec):
            said = "withdrawn" if rec.get("retract") else \
                f"labelled {rec.get('fabric')}{' (off-scene)' if rec.get('off_scene') else ''}"
            fate[str(rec["item_id"])] = f"{said}: " + ("applied" if rec.get("applied") else
                                                      f"not applied ({rec.get('why', '?')})")
    waiting = {str(r["item_id"]): "withdrawn" if r.get("retract") else
               f"labelled {r['fabric']}{' (off-scene)' if r.get('off_scene') else ''}"
               for _, r in read_labels(cfg.operator_labels) if isinstance(r, dict)}
    if not last:
        return [f"no piece in the reject bin in {cfg.journal}"]
    out = [f"the last {len(last)} piece(s) in the reject bin ({cfg.journal}), oldest first:"]
    for rec, stopped in last:
        item = str(rec.get("item_id", ""))
        label = fate.get(item) or (f"{waiting[item]}: the service reads it before its next piece"
                                   if item in waiting else "no label yet")
        why = rec.get("reason") or ("" if rec.get("outcome") == "sorted" else str(rec.get("outcome", ""))) \
            or reject_reason(str(rec.get("label", "")), stopped)
        out.append(f"  {item:>14s}  decision {rec.get('label', '?'):>14s}  {why:<12.60s}  {label}")
    return out
