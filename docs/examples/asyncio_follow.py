"""The asyncio face: the same program as claim_and_follow.py, as coroutines.

python docs/examples/asyncio_follow.py [ENDPOINT] [SECONDS]
"""

import asyncio
import math
import sys

import busgate.client as bc


async def main(endpoint: str, seconds: float) -> None:
    async with bc.aio.connect(endpoint, client_id="example-aio") as c:
        la1 = await c.device("la1")
        print("la1 at", (await la1.state()).position)
        async with la1.claim(ttl_s=2.0), la1.follow() as stream:
            loop = asyncio.get_running_loop()
            start = loop.time()
            while (t := loop.time() - start) < seconds:
                stream.set(position=round(1000 + 600 * math.sin(2 * math.pi * 0.5 * t)))
                await asyncio.sleep(0.02)
        samples = [state.position async for state in la1.states(timeout=0.5)]
        print(f"streamed {seconds:g} s; then {len(samples)} states in 0.5 s")


endpoint = sys.argv[1] if len(sys.argv) > 1 else "tcp/127.0.0.1:7447"
asyncio.run(main(endpoint, float(sys.argv[2]) if len(sys.argv) > 2 else 5.0))
