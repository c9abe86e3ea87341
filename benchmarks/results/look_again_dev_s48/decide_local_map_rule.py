"""(As run at stop 48, from a scratch folder; the rule itself is in docs/results.md.) Apply stop 48's local-map rule: candidate JSONs vs the ON JSONs of stops 45/46 (+ stop 47's ON CPU-s)."""
import glob, json, os, statistics as st, sys
S = "/work/scratch/23/s48/cand"  # committed copy: benchmarks/results/look_again_dev_s48/local_map_0_16
ON = {"s46": "/work/wt/23/benchmarks/results/look_again_dev_s46/on", "s45": "/work/wt/23/benchmarks/results/look_again_dev_s45/D"}
REF = ["/work/scratch/23/ref", "/work/scratch/23/new_run"]  # stop 47: today's-code ON, cpu_s (base, branch)
rows = []
for part in ("s46", "s45"):
    for f in sorted(glob.glob(f"{S}/{part}/*.json")):
        c = json.load(open(f)); o = json.load(open(os.path.join(ON[part], os.path.basename(f))))
        ph = c.get("phases", {})
        rows.append((part, os.path.basename(f), o, c, ph))
W = L = 0
for part, name, o, c, ph in rows:
    w = c["success"] and not o["success"]; l = o["success"] and not c["success"]
    W += w; L += l
    lm = ph.get("nvsm_local_map", ph.get("local_map", {}))
    print(f"{c['house_seed']}/{c['episode_id']}: ON {'S' if o['success'] else 'F'} {o['steps']} {o['spl']:.3f} | cand {'S' if c['success'] else 'F'} {c['steps']} {c['spl']:.3f} "
          f"cpu {c['cpu_s']} wall {c['wall_s']} load {c.get('load1_start')} nvsm {o['nvsm_runs']}->{c['nvsm_runs']} {'WIN' if w else ''}{'LOSS' if l else ''}")
n = len(rows)
so = sum(o["success"] for _, _, o, _, _ in rows); sc = sum(c["success"] for _, _, _, c, _ in rows)
mo = sum(o["spl"] for _, _, o, _, _ in rows) / max(n, 1); mc = sum(c["spl"] for _, _, _, c, _ in rows) / max(n, 1)
print(f"n={n}: successes ON {so} cand {sc}; paired wins {W} losses {L}; mean SPL ON {mo:.3f} cand {mc:.3f} (diff {mc - mo:+.3f})")
ratios = []
for part, name, o, c, ph in rows:
    refs = [json.load(open(os.path.join(d, name)))["cpu_s"] for d in REF if os.path.exists(os.path.join(d, name))]
    if refs:
        on_cpu = sum(refs) / len(refs)
        ratios.append(c["cpu_s"] / on_cpu)
        print(f"  speed {name}: ON cpu {refs} mean {on_cpu:.1f} -> cand {c['cpu_s']} ratio {c['cpu_s'] / on_cpu:.3f}")
if ratios:
    print(f"speed: {len(ratios)} episodes, median ratio {st.median(ratios):.3f}")
ok = n >= 16 and sc >= so and L <= W and mc >= mo - 0.01 and len(ratios) == 8 and st.median(ratios) <= 0.90
print("RULE:", "PASS" if ok else "FAIL")
