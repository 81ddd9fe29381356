"""Issue 39 point 3: a wrong user name or password is said in plain words, in the HMI's login box and
in ``uacell health``, never as "BadUserAccessDenied: User does not have permission to perform the
requested operation"."""

from __future__ import annotations

import pytest
import pytest_asyncio
from conftest import fast_config, start_app
from test_web import PASSWORD, Browser

from uacell.cli.health import check
from uacell.core.errors import WRONG_CREDENTIALS, login_refusal
from uacell.security.pki import PkiPaths
from uacell.web.hosting import start_web, trust_hmi

pytestmark = pytest.mark.asyncio(loop_scope="module")


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def stack(tmp_path_factory):
    data = tmp_path_factory.mktemp("loginwords") / "data"
    app = await start_app(fast_config(data))
    app.users.add("otto", "operator", PASSWORD)
    trust_hmi(data)
    web = await start_web(
        app.endpoint, data, companions=app.companions, port=0, server_certificate=PkiPaths.in_data_dir(data).cert
    )
    try:
        yield app, web
    finally:
        await web.stop()
        await app.stop()


async def test_the_hmi_login_says_the_user_name_or_password_is_wrong(stack):
    _app, web = stack
    for user, password in (("otto", "not-his-password"), ("nobody", PASSWORD)):
        b = Browser(web.url)
        await b.start()
        status, answer = await b.login(user, password)
        assert status == 401
        assert answer["error"] == "The user name or password is wrong"
        assert answer["code"] == "BadUserAccessDenied"
        assert "permission" not in answer["error"]
    b = Browser(web.url)
    await b.start()
    assert (await b.login("otto"))[0] == 200  # the right one still gets in


async def test_uacell_health_with_wrong_credentials_says_so(stack):
    app, _web = stack
    host_port = app.endpoint.removeprefix("opc.tcp://")
    ok, message = await check(f"opc.tcp://otto:not-his-password@{host_port}", timeout=20)
    assert not ok
    assert message == "the server refused the login: the user name or password is wrong (BadUserAccessDenied)"
    ok, message = await check(f"opc.tcp://otto:{PASSWORD}@{host_port}", timeout=20)
    assert (ok, message) == (True, "Running")


async def test_only_credential_refusals_get_these_words() -> None:
    assert login_refusal("BadUserAccessDenied") == WRONG_CREDENTIALS
    assert login_refusal("BadTooManySessions") is None
