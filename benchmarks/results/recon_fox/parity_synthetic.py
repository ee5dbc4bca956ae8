import sys, torch
sys.path.insert(0, "/tmp/ht/oldpkg"); sys.path.insert(0, "tests/recon")
from synthscene import ground_truth, render_views, sphere_cameras
import recon_old
from tiger.recon import ReconConfig, Trainer
gt = ground_truth(20, seed=3); cams = sphere_cameras(10, size=24); imgs = render_views(gt, cams)
kw = dict(iterations=120, sh_degree=1, sh_increase_every=15, densify_from=5, densify_until=100,
          densify_interval=10, opacity_reset_interval=30, init_random_points=60, progress=False,
          random_background=True, lr_means_init=1e-3, max_world_size=0.05)
a = recon_old.Trainer(cams, imgs, recon_old.ReconConfig(**kw)); a.fit()
b = Trainer(cams, imgs, ReconConfig(**kw)); b.fit()
print(len(a.scene), len(b.scene), "EQUAL" if a.scene.detach().equal(b.scene.detach()) else "DIFFERENT")
sa, sb = a.optimizer.state_dict(), b.optimizer.state_dict()
print("opt equal", all(torch.equal(sa["state"][k][n], sb["state"][k][n]) for k in sa["state"] for n in ("exp_avg","exp_avg_sq")))
# old checkpoint resumes in the new trainer
a2 = recon_old.Trainer(cams, imgs, recon_old.ReconConfig(**kw))
for _ in range(60): a2.train_step()
a2.save("/tmp/ht/old_ck.pt")
c = Trainer(cams, imgs, ReconConfig(**kw)); c.load("/tmp/ht/old_ck.pt"); c.fit()
print("old checkpoint resumed in new trainer:", "EQUAL" if c.scene.detach().equal(a.scene.detach()) else "DIFFERENT")
