# the state of a read-only handle on the same store, used as a rollback point
import tempfile, warnings, torch
warnings.simplefilter("ignore")
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem import ZarrStorage
path = tempfile.mkdtemp() + "/m.zarr"
rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 8, goal_conditioned=False), batch_size=2)
rb.extend(TensorDict({"obs": torch.arange(6.0).unsqueeze(-1)}, [6]))
rb.storage.flush()
reader = ZarrStorage(path, read_only=True)
sd = reader.state_dict()
print("reader row_file", reader.row_file)
rb.extend(TensorDict({"obs": torch.arange(100.0, 106.0).unsqueeze(-1)}, [6]))  # wraps: rows 6,7,0..3 overwritten
rb.storage.flush()
print("state rows now:", sd["_storage"]["obs"][:8].flatten().tolist(), "state _len", sd["_len"])
try:
    rb.storage.load_state_dict(sd)
    print("loaded: len", len(rb), rb.storage[:]["obs"].flatten().tolist())
except Exception as e:
    print(type(e).__name__, str(e)[:200])
