"""Plain-text tables for the terminal."""


def _vec(v, digits=3):
    return "(" + ", ".join(f"{x:.{digits}f}" for x in v) + ")"


def features_table(inv):
    """The CAD feature inventory as an aligned text table (part frame, mm)."""
    rows = [("id", "kind", "geometry (part frame, mm)", "length", "faces")]
    for f in inv.features:
        if f.kind == "line":
            geom = f"{_vec(f.start)} -> {_vec(f.end)}"
        else:
            geom = f"centre {_vec(f.center)} normal {_vec(f.normal)} r {f.radius:.4f}"
            if f.kind == "arc":
                import math

                geom += f" {math.degrees(f.angle_end - f.angle_start):.1f} deg"
        rows.append((f.id, f.kind, geom, f"{f.length:.3f}", " ".join(f.faces)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    counts = {}
    for f in inv.features:
        counts[f.kind] = counts.get(f.kind, 0) + 1
    lines.append("")
    lines.append(", ".join(f"{n} {k}s" for k, n in sorted(counts.items())) or "no line, circle or arc edges")
    return "\n".join(lines)
