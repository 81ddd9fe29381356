"""Who may log in and as what: uacell's user manager for asyncua, and per-session User* attributes."""

from __future__ import annotations

import contextvars
import logging
from typing import Any

from asyncua import ua

from uacell.core.roles import ACTION_ROLES, ListeningPolicy, Role
from uacell.security.certificate_login import VerifiedCertificate
from uacell.security.users import UserStore
from uacell.ua.context import UacellUser

log = logging.getLogger(__name__)

#: (user name, password, role or None) checked for the ActivateSession under way, so that ``get_user``
#: (which asyncua calls synchronously on the event loop) need not hash the password again.
verified_login: contextvars.ContextVar[tuple[str, str, Role | None] | None] = contextvars.ContextVar(
    "uacell_verified_login", default=None
)


class UacellUserManager:
    """asyncua calls ``get_user`` at ActivateSession; None refuses the session (Bad_UserAccessDenied)."""

    def __init__(self, policy: ListeningPolicy, users: UserStore) -> None:
        self.policy = policy
        self.users = users

    def get_user(
        self, iserver: Any, username: str | None = None, password: str | None = None, certificate: Any = None
    ) -> UacellUser | None:
        if isinstance(certificate, VerifiedCertificate):  # an X509IdentityToken (decision 84)
            login = certificate.login
            user = UacellUser(login.user, login.role.label, certificate=True)
            user.expires = login.expires
            user.certificate = login.thumbprint
            return user
        if username is None:  # (``certificate`` is then the channel's application certificate, if any)
            return UacellUser(None, self.policy.anonymous_role.label, anonymous=True)
        checked = verified_login.get()
        if checked is not None and checked[:2] == (username, password or ""):
            role = checked[2]
        else:
            role = self.users.verify(username, password or "")
        if role is None:
            log.info("refused login of user %r: wrong user name or password", username)
            return None
        user = UacellUser(username, Role.parse(role).label)
        user.password_hash = self.users.password_hash(username)
        return user


def user_access_level(role: str, access_level: int, needed: Role | None = None) -> int:
    """The UserAccessLevel ``role`` gets for a variable with ``access_level`` whose writes need ``needed``
    (default: the ``write`` action of the role table)."""
    if Role.parse(role) >= (needed if needed is not None else ACTION_ROLES["write"]):
        return access_level
    write: int = ua.AccessLevel.CurrentWrite.mask
    return access_level & ~write
