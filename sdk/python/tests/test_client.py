"""kairos-client against a live `kairos serve` (see conftest.py)."""

import asyncio
import re

import numpy as np
import pytest

import kairos


def observation(client: kairos.Client, step: int = 0) -> dict:
    state_dim = client.model["state_dim"]
    return {
        "state": np.linspace(0.0, 1.0, state_dim, dtype=np.float32) + 0.01 * step,
        "images": {"front": np.full((8, 8, 3), step % 256, dtype=np.uint8)},
        "instruction": "pick up the cube",
    }


@pytest.fixture
def client(server):
    with kairos.Client.from_data_dir(server.data_dir, server.address) as client:
        yield client


def test_version_is_the_crate_version():
    assert re.fullmatch(r"\d+\.\d+\.\d+", kairos.__version__)


def test_infer_returns_a_finite_chunk_of_the_model_shape(client):
    model = client.model
    actions = client.infer(observation(client))
    assert isinstance(actions, np.ndarray)
    assert actions.dtype == np.float32
    assert actions.ndim == 2
    assert 1 <= actions.shape[0] <= model["chunk_len"]
    assert actions.shape[1] == model["action_dim"]
    assert np.isfinite(actions).all()
    assert np.abs(actions).sum() > 0, "a real forward pass, not zeros"
    assert not actions.flags.owndata, "a view of the reply's buffer, not a copy"
    last = client.last_round
    assert last["horizon"] == actions.shape[0] and last["chunk_len"] == model["chunk_len"]
    assert last["round"] == 0 and last["attempts"] == 1 and last["batch_size"] >= 1
    assert last["task"] == client.task_id


def test_actions_taken_from_the_queue_are_reported_with_the_next_round(client):
    task = client.start_task(control_hz=50.0, trigger=0.5)
    first = client.infer(observation(client, 0))
    assert client.queue_size == first.shape[0]
    taken = [client.next_action() for _ in range(first.shape[0])]
    np.testing.assert_array_equal(np.stack(taken), first)
    assert client.next_action() is None and client.queue_size == 0
    assert client.wants_request()
    client.infer(observation(client, 1))
    record = client.end_task()
    assert record["task"] == task
    assert record["rounds"] == 2
    assert client.task_id is None


def test_one_round_per_task_at_a_time_and_asyncio(client):
    async def main():
        client.start_task()
        pending = client.infer_async(observation(client, 0))
        assert client.in_flight
        with pytest.raises(kairos.TaskError, match="in flight"):
            client.infer(observation(client, 1))
        with pytest.raises(kairos.TaskError):
            client.end_task()
        actions = await pending
        assert actions.shape[1] == client.model["action_dim"]
        assert not client.in_flight
        again = await client.infer_async(observation(client, 2))
        assert np.isfinite(again).all()
        return client.end_task()

    assert asyncio.run(main())["rounds"] == 2


def test_two_robots_infer_concurrently_from_asyncio(server):
    async def main():
        clients = [kairos.Client.from_data_dir(server.data_dir, server.address) for _ in range(2)]
        try:
            chunks = await asyncio.gather(*(c.infer_async(observation(c)) for c in clients))
            return [chunk.shape for chunk in chunks]
        finally:
            for c in clients:
                c.close()

    shapes = asyncio.run(main())
    assert len(shapes) == 2 and all(len(shape) == 2 for shape in shapes)


def test_a_wrong_token_is_refused_with_a_typed_error(server):
    with pytest.raises(kairos.Unauthorized) as refused:
        kairos.Client(server.address, server.fingerprint, "not-the-token")
    assert isinstance(refused.value, kairos.KairosError)
    assert refused.value.code == "unauthorized"
    assert not refused.value.retryable


def test_a_wrong_pin_is_refused_with_a_typed_error(server):
    with pytest.raises(kairos.PinMismatch):
        kairos.Client(server.address, "sha256:" + "00" * 32, server.token)


def test_a_bad_observation_raises_a_typed_error_naming_the_field(client):
    # Caught by the client: the state is not an array.
    with pytest.raises(kairos.InvalidObservation, match=r'observation\["state"\]'):
        client.infer({"state": "not an array"})
    with pytest.raises(kairos.InvalidObservation, match=r'observation\["images"\]\["front"\]'):
        client.infer({"state": observation(client)["state"], "images": {"front": b"GIF89a"}})
    with pytest.raises(kairos.InvalidObservation, match="state.*missing"):
        client.infer({"instruction": "no state"})
    # Caught by the server: the state has the wrong length for the model.
    wrong = np.zeros(client.model["state_dim"] + 3, dtype=np.float32)
    with pytest.raises(kairos.InvalidObservation, match="state") as refused:
        client.infer({"state": wrong})
    assert refused.value.code == "invalid_observation"
    # The client and its task are still usable.
    assert np.isfinite(client.infer(observation(client))).all()


def test_the_client_resumes_after_a_server_restart(server):
    client = kairos.Client.from_data_dir(server.data_dir, server.address, reconnect_attempts=12)
    try:
        client.start_task()
        client.infer(observation(client, 0))
        assert client.stats["connects"] == 1
        server.restart()  # same data directory (certificate, token) and port
        actions = client.infer(observation(client, 1))
        assert np.isfinite(actions).all()
        assert client.stats["connects"] == 2, "a second connection, made by the client itself"
        assert client.last_round["round"] == 1
    finally:
        client.close()
