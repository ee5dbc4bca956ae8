"""Run benchmarks/recon_fox.py with the pre-refactor tiger.recon (main at 25d39ee)."""
import sys
sys.path.insert(0, "/tmp/ht/oldpkg")
import recon_old, tiger
sys.modules["tiger.recon"] = recon_old
tiger.recon = recon_old
sys.path.insert(0, "/work/wt/house-train/benchmarks")
import recon_fox
raise SystemExit(recon_fox.main(sys.argv[1:]))
