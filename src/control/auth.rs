//! Who may control the daemon: the peer's credentials (SO_PEERCRED) against root, the
//! daemon's own user and `daemon.group` (from /etc/passwd and /etc/group). Anyone who can
//! open the socket may read.

use std::path::{Path, PathBuf};

/// Why the control group could not be read.
#[derive(Debug, thiserror::Error)]
pub enum AuthError {
    #[error("cannot read {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path}: group {group} has a bad gid {gid:?}")]
    BadGid { path: PathBuf, group: String, gid: String },
    #[error("group `{0}` (daemon.group) does not exist; create it (groupadd {0}) or set daemon.group = \"\"")]
    NoGroup(String),
}

/// Who may control the daemon (SO_PEERCRED): root, the daemon's own user, and members of
/// the configured group (primary or supplementary, from /etc/passwd and /etc/group).
#[derive(Debug, Clone)]
pub struct Auth {
    pub daemon_uid: u32,
    /// (name, gid, member user names).
    pub group: Option<(String, u32, Vec<String>)>,
    /// uid → (user name, primary gid), from /etc/passwd.
    pub users: Vec<(u32, String, u32)>,
}

impl Auth {
    /// Reads the group from `/etc/group` (an empty name: no group).
    pub fn load(group: &str) -> Result<Auth, AuthError> {
        Auth::from_files(group, Path::new("/etc/group"), Path::new("/etc/passwd"))
    }

    pub fn from_files(group: &str, group_file: &Path, passwd_file: &Path) -> Result<Auth, AuthError> {
        // SAFETY: geteuid has no preconditions.
        let daemon_uid = unsafe { libc::geteuid() };
        let users = std::fs::read_to_string(passwd_file)
            .unwrap_or_default()
            .lines()
            .filter_map(|l| {
                let f: Vec<&str> = l.split(':').collect();
                Some((f.get(2)?.parse().ok()?, f.first()?.to_string(), f.get(3)?.parse().ok()?))
            })
            .collect();
        if group.is_empty() {
            return Ok(Auth { daemon_uid, group: None, users });
        }
        let text = std::fs::read_to_string(group_file).map_err(|source| AuthError::Read { path: group_file.to_path_buf(), source })?;
        for line in text.lines() {
            let f: Vec<&str> = line.split(':').collect();
            if f.len() >= 4 && f[0] == group {
                let gid = f[2].parse().map_err(|_| AuthError::BadGid { path: group_file.to_path_buf(), group: group.to_string(), gid: f[2].to_string() })?;
                let members = f[3].split(',').filter(|m| !m.is_empty()).map(str::to_string).collect();
                return Ok(Auth { daemon_uid, group: Some((group.to_string(), gid, members)), users });
            }
        }
        Err(AuthError::NoGroup(group.to_string()))
    }

    /// May the peer `uid`/`gid` control scans? `groups` are the peer's own supplementary
    /// groups at connect time (`SO_PEERGROUPS`): a member added later gets in without a
    /// restart, a process that dropped its groups does not. Where the kernel cannot tell
    /// (None), the group file read at start decides.
    pub fn may_control(&self, uid: u32, gid: u32, groups: Option<&[u32]>) -> bool {
        if uid == 0 || uid == self.daemon_uid {
            return true;
        }
        let Some((_, group_gid, members)) = &self.group else { return false };
        if gid == *group_gid {
            return true;
        }
        match groups {
            Some(g) => g.contains(group_gid),
            None => self.users.iter().any(|(u, name, primary)| *u == uid && (primary == group_gid || members.contains(name))),
        }
    }
}

/// `SO_PEERGROUPS` (Linux ≥ 4.13; not in every libc binding).
const SO_PEERGROUPS: libc::c_int = 59;

/// The supplementary groups of the process at the other end of a Unix socket, as they were
/// when it connected; None when the kernel does not say.
pub fn peer_groups(fd: std::os::fd::RawFd) -> Option<Vec<u32>> {
    let mut groups = vec![0 as libc::gid_t; 64];
    loop {
        let mut len = (groups.len() * std::mem::size_of::<libc::gid_t>()) as libc::socklen_t;
        // SAFETY: the buffer holds `len` bytes; the kernel writes at most that and sets `len`.
        let r = unsafe { libc::getsockopt(fd, libc::SOL_SOCKET, SO_PEERGROUPS, groups.as_mut_ptr().cast(), &mut len) };
        if r == 0 {
            groups.truncate(len as usize / std::mem::size_of::<libc::gid_t>());
            return Some(groups);
        }
        // ERANGE: the buffer is too small; `len` says how much is needed.
        if std::io::Error::last_os_error().raw_os_error() == Some(libc::ERANGE) && (len as usize) > groups.len() * std::mem::size_of::<libc::gid_t>() {
            groups.resize(len as usize / std::mem::size_of::<libc::gid_t>() + 1, 0);
            continue;
        }
        return None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_is_for_root_the_daemon_and_the_group() {
        let dir = std::env::temp_dir().join(format!("spinscan-auth-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("group"), "root:x:0:\nspinscan:x:1500:alice,bob\nother:x:1600:\n").unwrap();
        std::fs::write(dir.join("passwd"), "alice:x:2001:100::/:/bin/sh\ncarol:x:2003:1500::/:/bin/sh\nmallory:x:2004:1600::/:/bin/sh\n").unwrap();
        let auth = Auth::from_files("spinscan", &dir.join("group"), &dir.join("passwd")).unwrap();
        assert!(auth.may_control(0, 0, None), "root");
        assert!(auth.may_control(auth.daemon_uid, 12345, None), "the daemon's user");
        assert!(auth.may_control(2001, 100, None), "a listed member");
        assert!(auth.may_control(2003, 1500, None), "primary group");
        assert!(auth.may_control(2222, 1500, None), "peer gid is the group");
        // The caller's own groups decide when the kernel gives them: one added to the group
        // after the daemon started gets in, a listed member that dropped its groups does not.
        assert!(auth.may_control(2004, 1600, Some(&[1600, 1500])), "a member added later");
        assert!(!auth.may_control(2001, 100, Some(&[100])), "dropped its groups");
        if auth.daemon_uid != 2004 {
            assert!(!auth.may_control(2004, 1600, None), "not in the group");
        }
        let e = Auth::from_files("nosuch", &dir.join("group"), &dir.join("passwd")).unwrap_err().to_string();
        assert!(e.contains("nosuch") && e.contains("groupadd"), "{e}");
        let none = Auth::from_files("", &dir.join("group"), &dir.join("passwd")).unwrap();
        if none.daemon_uid != 2001 {
            assert!(!none.may_control(2001, 1500, None));
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
